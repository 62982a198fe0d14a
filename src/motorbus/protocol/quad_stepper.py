"""The 9-byte "FF AA" 4-axis stepper controller protocol (doc 001, docs/protocols.md part B).

Pure code: no asyncio, no clock, no I/O.

Frames::

    request  FF AA b2 b3 b4 b5 b6 b7 CS    CS = sum8(b0..b7), FF and AA included
    reply    FF AA r2 r3 r4 r5             no checksum, no length byte

``b2`` is the address: a motor 1..4, ``0x09`` all motors, ``0x00`` the I/O (LEDs), or
``0xBC`` save.  Every request is answered with one 6-byte *ack*.  Run and LED
commands later send a second 6-byte *done* reply when the action has finished.

Decoded replies are :class:`Ack` and :class:`Done` (both :class:`QuadReply`): the raw
reply bytes ``r2`` and ``r3`` as ``address`` and ``command``, the LED number for LED
replies, and the raw frame.  A run ack or done addressed to ``0x00`` (as the manual
documents, A1-02) cannot say which motor it is for, so its ``motor`` is ``None``.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import ClassVar, Self

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol import ff_aa
from motorbus.protocol.base import (
    FF_AA,
    Command,
    Family,
    FrameShape,
    check_int,
    format_hex,
)
from motorbus.protocol.families import DEFAULT_BAUD as DEFAULT_BAUDS
from motorbus.protocol.ff_aa import RotationDirection, check_direction

__all__ = [
    "ADDRESS_ALL",
    "ADDRESS_IO",
    "ADDRESS_SAVE",
    "DEFAULT_BAUD",
    "LED_ALL",
    "MOTORS",
    "REPLY_SIZE",
    "REQUEST_SIZE",
    "AccelAndSpeed",
    "Ack",
    "DirectionAndStartFrequency",
    "Done",
    "Home",
    "MotorSetup",
    "QuadCommand",
    "QuadReply",
    "RotationDirection",
    "Run",
    "RunAll",
    "RunPulses",
    "Save",
    "SetLed",
    "Stop",
    "StopAll",
    "build_request",
    "decode_reply_context_free",
    "decode_request",
    "is_done_reply",
    "request_is_valid",
]

# --- frame layout --------------------------------------------------------------------------

REQUEST_SIZE = 9  # doc 001 "协议采用9个字节每帧" (docs/protocols.md B.2)
REPLY_SIZE = ff_aa.REPLY_SIZE  # doc 001, every "回" line is 6 bytes (docs/protocols.md B.2)
_BODY_SIZE = REQUEST_SIZE - len(FF_AA) - 1  # b2..b7: header and checksum excluded
#: Not stated by doc 001; its vendor's sibling controller (doc 000) runs 9600 8N1 (A1-01).
DEFAULT_BAUD = DEFAULT_BAUDS[Family.QUAD_STEPPER]

# --- addresses (b2) ------------------------------------------------------------------------

MOTOR_MIN = 1  # doc 001 "电机1对应0x01"; four axes (A1-08)
MOTOR_MAX = 4  # doc 001 title "控制4路步进电机"
MOTORS = tuple(range(MOTOR_MIN, MOTOR_MAX + 1))
ADDRESS_IO = 0x00  # doc 001 section 十一 (LED control, b2 = 0x00)
ADDRESS_ALL = 0x09  # doc 001 sections 九/十 (all motors)
ADDRESS_SAVE = 0xBC  # doc 001 section 十二 (save)
#: The single-motor run ack and done are addressed to 0x00, not the motor (doc 001 七, A1-02).
RUN_REPLY_ADDRESS = 0x00

# --- commands (b3) -------------------------------------------------------------------------

CMD_MOTOR_SETUP = 0x01  # doc 001 section 一: subdivision + step angle
CMD_RUN_PULSES = 0x03  # doc 001 section 三: pulse count (A1-05)
CMD_DIRECTION = 0x04  # doc 001 section 四: direction + start (= homing) frequency
CMD_ACCEL_SPEED = 0x05  # doc 001 section 五: accel/decel (= homing accel) + speed RPM
CMD_STOP = 0x06  # doc 001 sections 八 (one motor) and 十 (all motors)
CMD_RUN = 0x09  # doc 001 sections 七 (one motor) and 九 (all motors)
CMD_LED = 0x0C  # doc 001 section 十一
CMD_HOME = 0x0F  # doc 001 section 六

# --- reply flags ---------------------------------------------------------------------------

FLAG_ACK = 0x00  # doc 001 "回 ... 0x00": command received
#: doc 001 "运行到位回" / "操作到位回"; in r4 for a run, in r5 for an LED (A1-03).
FLAG_DONE = 0x01

# --- value ranges --------------------------------------------------------------------------

U8_MAX = 0xFF
U16_MAX = 0xFFFF  # two-byte fields, low byte first (doc 001; A1-06 for accel)
U24_MAX = 0xFFFFFF  # three-byte pulse count (doc 001 section 三)
SUBDIVISION_MIN = 1  # 0 would make pulses/rev zero (doc 001 section 二 gear ratio)
#: Step angle in degrees x 100 in one byte: 1.8 deg -> 180, at most 2.55 deg (doc 001 section 一).
STEP_ANGLE_X100_MIN = 1
STOP_INPUT_NONE = 0  # doc 001 section 六: 0 = no stop input, homing starts at once (A1-10)
STOP_INPUT_MAX = 0x0D  # doc 001 section 六: 0x01..0x0D = YL1..YL13
LED_MIN = 1  # doc 001 section 十一: 0x01 = LED1
LED_ALL = 5  # doc 001 section 十一: 0x05 = all LEDs
LED_COUNT = 4  # doc 001 section 十一: LED1..LED4


_direction = check_direction


# --- framing helpers -----------------------------------------------------------------------


def request_is_valid(raw: bytes | bytearray | memoryview) -> bool:
    """Return True if ``raw`` is a complete request: 9 bytes, ``FF AA`` header, checksum right.

    Args:
        raw: the candidate frame.

    Returns:
        True for a well-formed frame; the command itself is not checked.
    """
    return ff_aa.request_is_valid(raw, REQUEST_SIZE)


def build_request(b2_to_b7: bytes) -> bytes:
    """Frame six payload bytes: prepend ``FF AA`` and append the checksum.

    Args:
        b2_to_b7: the address, command and four parameter bytes.

    Returns:
        The 9-byte request.

    Raises:
        LocalProtocolError: if ``b2_to_b7`` is not exactly 6 bytes.
    """
    size = len(bytes(b2_to_b7))
    return ff_aa.frame_request(
        b2_to_b7,
        _BODY_SIZE,
        "b2_to_b7",
        f"b2_to_b7 must be exactly {_BODY_SIZE} bytes, got {size}: allowed {_BODY_SIZE}",
    )


_reply_shape = ff_aa.reply_shape
_fits = ff_aa.fits


# --- decoded replies -----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class QuadReply:
    """A decoded 6-byte reply ``FF AA r2 r3 r4 r5`` (base of :class:`Ack` and :class:`Done`).

    Attributes:
        address: ``r2``: 1..4 a motor, 0x00 I/O or a single-motor run (A1-02), 0x09 all
            motors, 0xBC save.
        command: ``r3``: the command echoed (0x00 for save, whose opcode is ``r2``).
        led: the LED number 1..5 for LED replies (``00 0C L f``), else ``None``.
        raw: the 6 reply bytes.
    """

    address: int
    command: int
    led: int | None
    raw: bytes

    @property
    def motor(self) -> int | None:
        """The motor 1..4 this reply names, or ``None`` if it names none (run replies, A1-02)."""
        return self.address if MOTOR_MIN <= self.address <= MOTOR_MAX else None

    @classmethod
    def from_raw(cls, raw: bytes) -> Self:
        """Build the reply value from 6 bytes already known to fit a reply shape."""
        data = bytes(raw)
        led = data[4] if (data[2], data[3]) == (ADDRESS_IO, CMD_LED) else None
        return cls(data[2], data[3], led, data)


@dataclass(frozen=True, slots=True)
class Ack(QuadReply):
    """The immediate acknowledgement every request gets ("回" / "收到命令回" in doc 001)."""


@dataclass(frozen=True, slots=True)
class Done(QuadReply):
    """The later completion of a run or LED command ("运行到位回" / "操作到位回")."""


# --- commands ------------------------------------------------------------------------------


class QuadCommand(Command[Ack | Done]):
    """Common behaviour of every quad stepper request.

    Subclasses give the six bytes ``b2..b7`` and the shapes of their ack (and done) reply;
    framing, reply matching and decoding follow from those.
    """

    __slots__ = ()
    family: ClassVar[Family] = Family.QUAD_STEPPER

    @abc.abstractmethod
    def body(self) -> bytes:
        """Return the six bytes ``b2..b7`` of the request."""

    def encode(self) -> bytes:
        """Return the 9 request bytes, checksum included."""
        return build_request(self.body())

    def reply_lengths(self) -> tuple[int, ...]:
        """Every reply (ack and done) is 6 bytes."""
        return (REPLY_SIZE,)

    def matches_reply(self, raw: bytes) -> bool:
        """Return True if ``raw`` is the complete ack of this request."""
        return any(_fits(shape, raw) for shape in self.reply_shapes())

    def matches_done(self, raw: bytes) -> bool:
        """Return True if ``raw`` is a complete done reply of this request."""
        return any(_fits(shape, raw) for shape in self.done_shapes())

    def decode_reply(self, raw: bytes) -> Ack | Done:
        """Decode the ack or the done reply of this request.

        Args:
            raw: a 6-byte frame.

        Returns:
            :class:`Ack` for the ack, :class:`Done` for the done reply.

        Raises:
            RemoteProtocolError: if ``raw`` is neither.
        """
        data = bytes(raw)
        if self.matches_reply(data):
            return Ack.from_raw(data)
        if self.matches_done(data):
            return Done.from_raw(data)
        raise RemoteProtocolError(
            f"{format_hex(data)} is not a reply to {type(self).__name__}", raw=data
        )


def _check_motor(motor: object) -> int:
    return check_int("motor", motor, MOTOR_MIN, MOTOR_MAX)


class _MotorCommand(QuadCommand):
    """A per-motor command whose ack is ``FF AA M CMD 00 00``."""

    __slots__ = ()
    CMD: ClassVar[int]

    motor: int  # provided by the dataclass subclasses

    def params(self) -> bytes:
        """The four bytes ``b4..b7``."""
        return bytes(4)

    def body(self) -> bytes:
        """Return ``M CMD`` followed by the four parameter bytes."""
        return bytes((self.motor, self.CMD)) + self.params()

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """The ack ``FF AA M CMD 00 00`` (doc 001 sections 一..八)."""
        return (_reply_shape(self.motor, self.CMD, FLAG_ACK, 0x00),)


@dataclass(frozen=True, slots=True)
class MotorSetup(_MotorCommand):
    """Set a motor's driver subdivision and step angle (0x01, doc 001 section 一).

    Args:
        motor: 1..4.
        subdivision: microsteps per full step, 1..65535.
        step_angle_x100: full-step angle in degrees x 100, 1..255 (1.8 deg -> 180).
    """

    CMD: ClassVar[int] = CMD_MOTOR_SETUP
    motor: int
    subdivision: int
    step_angle_x100: int

    def __post_init__(self) -> None:
        _check_motor(self.motor)
        check_int("subdivision", self.subdivision, SUBDIVISION_MIN, U16_MAX)
        check_int("step_angle_x100", self.step_angle_x100, STEP_ANGLE_X100_MIN, U8_MAX)

    def params(self) -> bytes:
        """``SubL SubH Ang 00``."""
        return self.subdivision.to_bytes(2, "little") + bytes((self.step_angle_x100, 0))


@dataclass(frozen=True, slots=True)
class RunPulses(_MotorCommand):
    """Set the pulse count of the next run (0x03, doc 001 section 三, A1-05).

    Args:
        motor: 1..4.
        pulses: motor pulses, 0..16777215 (24 bits, unsigned; direction is set by 0x04).
    """

    CMD: ClassVar[int] = CMD_RUN_PULSES
    motor: int
    pulses: int

    def __post_init__(self) -> None:
        _check_motor(self.motor)
        check_int("pulses", self.pulses, 0, U24_MAX)

    def params(self) -> bytes:
        """``P0 P1 P2 00``."""
        return self.pulses.to_bytes(3, "little") + b"\x00"


@dataclass(frozen=True, slots=True)
class DirectionAndStartFrequency(_MotorCommand):
    """Set direction and start frequency, also used by homing (0x04, doc 001 section 四).

    Args:
        motor: 1..4.
        direction: :class:`RotationDirection` (an int 0/1 is accepted and converted).
        start_hz: start (and homing) pulse frequency in Hz, 0..65535.
    """

    CMD: ClassVar[int] = CMD_DIRECTION
    motor: int
    direction: RotationDirection
    start_hz: int

    def __post_init__(self) -> None:
        _check_motor(self.motor)
        object.__setattr__(self, "direction", _direction(self.direction))
        check_int("start_hz", self.start_hz, 0, U16_MAX)

    def params(self) -> bytes:
        """``Dir FL FH 00``."""
        return bytes((self.direction,)) + self.start_hz.to_bytes(2, "little") + b"\x00"


@dataclass(frozen=True, slots=True)
class AccelAndSpeed(_MotorCommand):
    """Set accel/decel frequency (also homing accel) and run speed (0x05, doc 001 section 五).

    Args:
        motor: 1..4.
        accel_hz: accel/decel "frequency", 0..65535, sent low byte first (A1-06); the manual
            gives no unit beyond Hz.
        speed_rpm: run speed in revolutions per minute, 0..65535.
    """

    CMD: ClassVar[int] = CMD_ACCEL_SPEED
    motor: int
    accel_hz: int
    speed_rpm: int

    def __post_init__(self) -> None:
        _check_motor(self.motor)
        check_int("accel_hz", self.accel_hz, 0, U16_MAX)
        check_int("speed_rpm", self.speed_rpm, 0, U16_MAX)

    def params(self) -> bytes:
        """``AL AH VL VH``."""
        return self.accel_hz.to_bytes(2, "little") + self.speed_rpm.to_bytes(2, "little")


@dataclass(frozen=True, slots=True)
class Home(_MotorCommand):
    """Start homing: run continuously with the 0x04/0x05 settings (0x0F, doc 001 section 六).

    Args:
        motor: 1..4.
        stop_input: 1..13 = input YL1..YL13 stops the motor; 0 = no stop input, the motor
            runs until Stop / StopAll (A1-10: prefer giving an input).
    """

    starts_motion: ClassVar[bool] = True
    CMD: ClassVar[int] = CMD_HOME
    motor: int
    stop_input: int = STOP_INPUT_NONE

    def __post_init__(self) -> None:
        _check_motor(self.motor)
        check_int("stop_input", self.stop_input, STOP_INPUT_NONE, STOP_INPUT_MAX)

    def params(self) -> bytes:
        """``Y 00 00 00``."""
        return bytes((self.stop_input, 0, 0, 0))


@dataclass(frozen=True, slots=True)
class Run(_MotorCommand):
    """Start one motor's run of the configured pulses (0x09, doc 001 section 七).

    The ack is ``FF AA 00 09 00 00`` and the done ``FF AA 00 09 01 00``: addressed to 0x00,
    not to the motor (A1-02), so both accept ``r2`` = 0x00 or the motor.

    Args:
        motor: 1..4.
    """

    starts_motion: ClassVar[bool] = True
    CMD: ClassVar[int] = CMD_RUN
    motor: int

    def __post_init__(self) -> None:
        _check_motor(self.motor)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """The ack ``FF AA {00,M} 09 00 00``."""
        return (_reply_shape(frozenset((RUN_REPLY_ADDRESS, self.motor)), CMD_RUN, FLAG_ACK, 0),)

    def done_shapes(self) -> tuple[FrameShape, ...]:
        """The done ``FF AA {00,M} 09 01 00`` (done flag in r4, A1-03)."""
        return (_reply_shape(frozenset((RUN_REPLY_ADDRESS, self.motor)), CMD_RUN, FLAG_DONE, 0),)


@dataclass(frozen=True, slots=True)
class Stop(_MotorCommand):
    """Stop one motor at once (0x06, doc 001 section 八); no done reply.

    Args:
        motor: 1..4.
    """

    CMD: ClassVar[int] = CMD_STOP
    motor: int

    def __post_init__(self) -> None:
        _check_motor(self.motor)


#: Addresses a run done may carry after RunAll: the documented 0x00, a motor (A1-02), or 0x09
#: in case a firmware echoes the RunAll address (A1-04: undocumented, accepted opportunistically).
_RUN_ALL_DONE_ADDRESSES = frozenset((RUN_REPLY_ADDRESS, ADDRESS_ALL, *MOTORS))


@dataclass(frozen=True, slots=True)
class RunAll(QuadCommand):
    """Start all four motors at once (``09 09``, doc 001 section 九).

    The manual documents only the ack; no completion (A1-04).  ``done_shapes`` gives the
    per-motor run done so that completions can be watched for opportunistically; do not
    block on them.
    """

    starts_motion: ClassVar[bool] = True

    def body(self) -> bytes:
        """``09 09 00 00 00 00``."""
        return bytes((ADDRESS_ALL, CMD_RUN, 0, 0, 0, 0))

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """The ack ``FF AA 09 09 00 00``."""
        return (_reply_shape(ADDRESS_ALL, CMD_RUN, FLAG_ACK, 0),)

    def done_shapes(self) -> tuple[FrameShape, ...]:
        """A per-motor run done ``FF AA {00,1..4,09} 09 01 00`` (opportunistic, A1-04)."""
        return (_reply_shape(_RUN_ALL_DONE_ADDRESSES, CMD_RUN, FLAG_DONE, 0),)


@dataclass(frozen=True, slots=True)
class StopAll(QuadCommand):
    """Stop all motors at once (``09 06``, doc 001 section 十); no done reply."""

    def body(self) -> bytes:
        """``09 06 00 00 00 00``."""
        return bytes((ADDRESS_ALL, CMD_STOP, 0, 0, 0, 0))

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """The ack ``FF AA 09 06 00 00``."""
        return (_reply_shape(ADDRESS_ALL, CMD_STOP, FLAG_ACK, 0),)


@dataclass(frozen=True, slots=True)
class SetLed(QuadCommand):
    """Switch an LED (``00 0C L S``, doc 001 section 十一).

    Args:
        led: 1..4 = LED1..LED4, 5 = all LEDs.
        on: True to light it.
    """

    led: int
    on: bool

    def __post_init__(self) -> None:
        check_int("led", self.led, LED_MIN, LED_ALL)
        if not isinstance(self.on, bool):
            raise LocalProtocolError(
                f"on must be a bool (False or True), got {self.on!r}", field="on", value=self.on
            )

    def body(self) -> bytes:
        """``00 0C L S 00 00``."""
        return bytes((ADDRESS_IO, CMD_LED, self.led, int(self.on), 0, 0))

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """The ack ``FF AA 00 0C L 00``."""
        return (_reply_shape(ADDRESS_IO, CMD_LED, self.led, FLAG_ACK),)

    def done_shapes(self) -> tuple[FrameShape, ...]:
        """The done ``FF AA 00 0C L 01`` (done flag in r5, A1-03)."""
        return (_reply_shape(ADDRESS_IO, CMD_LED, self.led, FLAG_DONE),)


@dataclass(frozen=True, slots=True)
class Save(QuadCommand):
    """Save the parameters set so far; the controller reloads them at power-up (``BC``, 十二)."""

    def body(self) -> bytes:
        """``BC 00 00 00 00 00``."""
        return bytes((ADDRESS_SAVE, 0, 0, 0, 0, 0))

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """The ack ``FF AA BC 00 00 00``."""
        return (_reply_shape(ADDRESS_SAVE, 0, 0, 0),)


# --- decoding without context --------------------------------------------------------------

_ANY_MOTOR = frozenset(MOTORS)
_MOTOR_ACK_COMMANDS = frozenset(
    (CMD_MOTOR_SETUP, CMD_RUN_PULSES, CMD_DIRECTION, CMD_ACCEL_SPEED, CMD_STOP, CMD_RUN, CMD_HOME)
)
_LEDS = frozenset(range(LED_MIN, LED_ALL + 1))

#: Every ack any request can get (a run ack addressed to its motor included, A1-02).
_ACK_SHAPES = (
    _reply_shape(_ANY_MOTOR, _MOTOR_ACK_COMMANDS, FLAG_ACK, 0),
    _reply_shape(RUN_REPLY_ADDRESS, CMD_RUN, FLAG_ACK, 0),
    _reply_shape(ADDRESS_ALL, frozenset((CMD_RUN, CMD_STOP)), FLAG_ACK, 0),
    _reply_shape(ADDRESS_IO, CMD_LED, _LEDS, FLAG_ACK),
    _reply_shape(ADDRESS_SAVE, 0, 0, 0),
)
#: Every done reply: a run (r2 as in RunAll.done_shapes) or an LED.
_DONE_SHAPES = (
    _reply_shape(_RUN_ALL_DONE_ADDRESSES, CMD_RUN, FLAG_DONE, 0),
    _reply_shape(ADDRESS_IO, CMD_LED, _LEDS, FLAG_DONE),
)


def is_done_reply(raw6: bytes) -> bool:
    """Return True if ``raw6`` is a complete run or LED done reply.

    Args:
        raw6: a candidate 6-byte reply.
    """
    data = bytes(raw6)
    return any(_fits(shape, data) for shape in _DONE_SHAPES)


def decode_reply_context_free(raw6: bytes) -> Ack | Done:
    """Classify a 6-byte reply without knowing the request (for ``motorbus decode``).

    Args:
        raw6: the reply bytes.

    Returns:
        :class:`Done` for a run/LED done reply, else :class:`Ack`.

    Raises:
        RemoteProtocolError: if the bytes fit no documented reply.
    """
    data = bytes(raw6)
    if is_done_reply(data):
        return Done.from_raw(data)
    if any(_fits(shape, data) for shape in _ACK_SHAPES):
        return Ack.from_raw(data)
    raise RemoteProtocolError(f"{format_hex(data)} is not a quad stepper reply", raw=data)


def _require_zero(raw: bytes, first: int) -> None:
    """Refuse nonzero spare bytes ``raw[first:8]``: every documented frame sends them as 00."""
    for i in range(first, REQUEST_SIZE - 1):
        if raw[i]:
            raise RemoteProtocolError(
                f"{format_hex(raw)}: spare byte b{i}=0x{raw[i]:02X} must be 00", raw=raw
            )


def _decode_motor(raw: bytes) -> QuadCommand:
    motor, cmd = raw[2], raw[3]
    if cmd == CMD_MOTOR_SETUP:
        _require_zero(raw, 7)
        return MotorSetup(motor, int.from_bytes(raw[4:6], "little"), raw[6])
    if cmd == CMD_RUN_PULSES:
        _require_zero(raw, 7)
        return RunPulses(motor, int.from_bytes(raw[4:7], "little"))
    if cmd == CMD_DIRECTION:
        _require_zero(raw, 7)
        return DirectionAndStartFrequency(
            motor, _direction(raw[4]), int.from_bytes(raw[5:7], "little")
        )
    if cmd == CMD_ACCEL_SPEED:
        return AccelAndSpeed(
            motor, int.from_bytes(raw[4:6], "little"), int.from_bytes(raw[6:8], "little")
        )
    if cmd == CMD_HOME:
        _require_zero(raw, 5)
        return Home(motor, raw[4])
    if cmd == CMD_RUN:
        _require_zero(raw, 4)
        return Run(motor)
    if cmd == CMD_STOP:
        _require_zero(raw, 4)
        return Stop(motor)
    raise RemoteProtocolError(f"{format_hex(raw)}: unknown motor command 0x{cmd:02X}", raw=raw)


def _decode_valid(raw: bytes) -> QuadCommand:
    address, cmd = raw[2], raw[3]
    if MOTOR_MIN <= address <= MOTOR_MAX:
        return _decode_motor(raw)
    if address == ADDRESS_ALL and cmd in (CMD_RUN, CMD_STOP):
        _require_zero(raw, 4)
        return RunAll() if cmd == CMD_RUN else StopAll()
    if address == ADDRESS_IO and cmd == CMD_LED:
        _require_zero(raw, 6)
        if raw[5] not in (0, 1):
            raise RemoteProtocolError(
                f"{format_hex(raw)}: LED state 0x{raw[5]:02X} must be 00 or 01", raw=raw
            )
        return SetLed(raw[4], bool(raw[5]))
    if address == ADDRESS_SAVE:
        _require_zero(raw, 3)
        return Save()
    raise RemoteProtocolError(
        f"{format_hex(raw)}: unknown address/command 0x{address:02X} 0x{cmd:02X}", raw=raw
    )


def decode_request(raw: bytes) -> QuadCommand:
    """Decode a 9-byte request into its command value (for the simulator and ``decode``).

    Spare bytes must be 00, as in every documented frame.

    Args:
        raw: the request bytes.

    Returns:
        The command; ``decode_request(cmd.encode()) == cmd`` for every command.

    Raises:
        RemoteProtocolError: if the frame is malformed (length, header, checksum), the
            address or command is unknown, a spare byte is not 00, or a value is out of
            range.  ``raw`` is attached.
    """
    data = bytes(raw)
    if not request_is_valid(data):
        raise RemoteProtocolError(
            f"{format_hex(data)} is not a {REQUEST_SIZE}-byte FF AA request with a valid checksum",
            raw=data,
        )
    try:
        return _decode_valid(data)
    except LocalProtocolError as err:
        raise RemoteProtocolError(f"{format_hex(data)}: {err}", raw=data) from err
