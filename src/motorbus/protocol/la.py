"""Inspire Robots micro servo linear actuator (LA/LAS/LAF/LASF/LAXC), "55 AA" UART protocol.

Doc 002 (manual PRJ-01-TS-U-004 V1.8.3), digested in docs/protocols.md part C.  Pure code: no
asyncio, no clock, no I/O.

Frames::

    request  55 AA Len ID CMD IDX D1 .. DN CS
    reply    AA 55 Len ID CMD IDX D1 .. DN CS
    Len = total - 5 (A2-01)        CS = (Len + ID + ... + DN) & 0xFF

Broadcast frames (0xF2/0xF3) carry no IDX byte; the same Len rule covers them.

Every request is a frozen ``Command`` value (``MoveTo``, ``Follow``, ``Control``, ``ReadTable``,
``ReadRegister``, ``WriteTable``, ``WriteRegister``, ``Broadcast``) that validates itself on
construction, encodes itself and recognises its own reply.  ``decode_reply`` and
``decode_request`` turn bytes back into values without knowing the request.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import ClassVar, NamedTuple

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import (
    LA_REPLY_HEADER,
    LA_REQUEST_HEADER,
    Command,
    Family,
    FaultState,
    ReplyT_co,
    check_choice,
    check_int,
    format_hex,
    sum8,
)
from motorbus.protocol.families import LA_BROADCAST_ID, LA_ID_MAX, LA_ID_MIN

__all__ = [
    "BROADCAST_ID",
    "CMD_BROADCAST_FOLLOW",
    "CMD_BROADCAST_MOVE",
    "CMD_CONTROL",
    "CMD_FOLLOW",
    "CMD_FOLLOW_NO_REPLY",
    "CMD_MOVE",
    "CMD_MOVE_NO_REPLY",
    "CMD_READ",
    "CMD_WRITE",
    "ID_MAX",
    "ID_MIN",
    "MAX_BROADCAST_ENTRIES",
    "MAX_FRAME_SIZE",
    "POSITION_MAX",
    "POSITION_MIN",
    "REPORTED_POSITION_MAX",
    "REPORTED_POSITION_MIN",
    "STATUS_FRAME_SIZE",
    "STATUS_LEN_BYTE",
    "TARGET_INDEX",
    "TEMPERATURE_GAP_C10",
    "WRITE_ACK_FRAME_SIZE",
    "BaudCode",
    "Broadcast",
    "BroadcastMode",
    "Control",
    "ControlAction",
    "ErrorFlags",
    "Follow",
    "MoveTo",
    "ReadRegister",
    "ReadReply",
    "ReadTable",
    "Register",
    "RegisterInfo",
    "Status",
    "UnknownReply",
    "WriteAck",
    "WriteRegister",
    "WriteTable",
    "build_frame",
    "decode_reply",
    "decode_request",
    "decode_status",
    "encode_status",
    "frame_is_valid",
    "la_checksum",
    "split_broadcast",
    "temperature_limit_writes",
]

# --- frame layout -----------------------------------------------------------------------

#: Bytes around Len's count: header (2) + Len (1) + ID (1) + CS (1); Len = total - 5 (A2-01).
FRAME_OVERHEAD = 5
#: Smallest meaningful frame: header, Len, ID, CMD, CS (Len = 1, a CMD and nothing else).
MIN_FRAME_SIZE = 6
#: Largest frame the one-byte Len allows (doc 002 section 3.3, Len is one byte).
MAX_FRAME_SIZE = 0xFF + FRAME_OVERHEAD

# --- addressing and values ----------------------------------------------------------------

#: ID 0xFF addresses every actuator; none replies (doc 002 section 3.3, C.2).
BROADCAST_ID = LA_BROADCAST_ID
#: Valid actuator IDs (doc 002 section 3.3, control table index 2).
ID_MIN = LA_ID_MIN
ID_MAX = LA_ID_MAX
#: Commanded target range, unitless, 0..100 % of stroke (doc 002 section 3.5.3, A2-08).
POSITION_MIN = 0
POSITION_MAX = 2000
#: Range of the *reported* current position (doc 002 section 3.6, index 26).
REPORTED_POSITION_MIN = -20
REPORTED_POSITION_MAX = 2020
#: At most 15 actuators per broadcast frame (doc 002 section 3.5.3, broadcast; A2-16).
MAX_BROADCAST_ENTRIES = 15
#: Control-table byte indices a single frame can address (index is one byte; 255 never used
#: because a read of N bytes must end at or before index 254, doc 002 section 3.6).
TABLE_INDEX_MAX = 254
#: Size of the control table in bytes (indices 0..254, doc 002 section 3.6).
TABLE_SIZE = TABLE_INDEX_MAX + 1

# --- command codes (doc 002 section 3.5, C.3) ---------------------------------------------

CMD_READ = 0x01  # CMD_RD: read control table (3.5.1)
CMD_WRITE = 0x02  # CMD_WR: write control table (3.5.2)
CMD_MOVE_NO_REPLY = 0x03  # positioning, no reply (3.5.3)
CMD_CONTROL = 0x04  # CMD_MC single control (3.5.4)
CMD_FOLLOW_NO_REPLY = 0x19  # follow (servo) mode, no reply (3.5.3)
CMD_FOLLOW = 0x20  # follow (servo) mode, status reply (3.5.3)
CMD_MOVE = 0x21  # positioning, status reply (3.5.3)
CMD_BROADCAST_MOVE = 0xF2  # broadcast positioning (3.5.3)
CMD_BROADCAST_FOLLOW = 0xF3  # broadcast follow (3.5.3)

#: Index of the target position register, the IDX byte of every motion frame (3.5.3, 3.6).
TARGET_INDEX = 0x37
#: Reserved IDX byte of CMD_MC frames: send 00 (doc 002 section 3.5.4, V6).
CONTROL_RESERVED = 0x00

# --- replies --------------------------------------------------------------------------------

#: Len byte of the 22-byte status frame (doc 002 section 3.5.4, C.4).
STATUS_LEN_BYTE = 0x11
#: Total size of the status frame (doc 002 section 3.5.4).
STATUS_FRAME_SIZE = STATUS_LEN_BYTE + FRAME_OVERHEAD
#: Len byte of the short write ack ``AA 55 03 ID 02 IDX 00 CS`` (doc 002 section 3.4.1, A2-03).
WRITE_ACK_LEN_BYTE = 0x03
#: Total size of the short write ack.
WRITE_ACK_FRAME_SIZE = WRITE_ACK_LEN_BYTE + FRAME_OVERHEAD
#: Len of a read request ``55 AA 03 ID 01 IDX N CS`` (doc 002 section 3.5.1).
READ_REQUEST_LEN_BYTE = 0x03
#: Len of a CMD_MC request ``55 AA 03 ID 04 00 SUB CS`` (doc 002 section 3.5.4).
CONTROL_LEN_BYTE = 0x03
#: Len of a motion request ``55 AA 04 ID CMD 37 PosL PosH CS`` (doc 002 section 3.5.3).
MOTION_LEN_BYTE = 0x04
#: A read reply's Len is N + 2 and must fit one byte, so N <= 253 (doc 002 section 3.4.1).
MAX_TABLE_BYTES = 0xFF - 2
#: Bytes per broadcast entry: ID, PosL, PosH (doc 002 section 3.5.3, A2-16: little-endian).
BROADCAST_ENTRY_SIZE = 3

#: Required gap between the over-temperature limit and the recovery temperature, in 0.1 degC:
#: over >= recovery + 5 degC (doc 002 section 3.6, indices 98 and 100; A2-14).
TEMPERATURE_GAP_C10 = 50


# --- frame helpers -----------------------------------------------------------------------------


def la_checksum(frame_without_cs: bytes | bytearray | memoryview) -> int:
    """Return the checksum of an LA frame given without its last (checksum) byte.

    Args:
        frame_without_cs: the frame from its two header bytes up to the last data byte.

    Returns:
        ``(Len + ID + CMD + ... + DN) & 0xFF``: the header is not summed (doc 002 section 3.3).
    """
    return sum8(bytes(frame_without_cs)[len(LA_REQUEST_HEADER) :])


def build_frame(header: bytes, body: bytes) -> bytes:
    """Build a complete LA frame: header, Len, body, checksum.

    Args:
        header: ``LA_REQUEST_HEADER`` (55 AA) or ``LA_REPLY_HEADER`` (AA 55).
        body: ``ID CMD IDX D1..DN`` (broadcasts: ``FF F2|F3 entries``), at least ID and CMD.

    Returns:
        The frame bytes with Len = total - 5 and the checksum appended.

    Raises:
        LocalProtocolError: unknown header, or a body too short or too long for one frame.
    """
    if header not in (LA_REQUEST_HEADER, LA_REPLY_HEADER):
        raise LocalProtocolError(
            f"header={format_hex(header)} is not allowed: use 55 AA or AA 55", field="header"
        )
    length = len(body) - 1  # Len counts CMD .. last data byte: the body minus its ID byte
    check_int("body length", len(body), 2, 0xFF + 1)
    without_cs = header + bytes((length,)) + bytes(body)
    return without_cs + bytes((la_checksum(without_cs),))


def frame_is_valid(raw: bytes | bytearray | memoryview) -> bool:
    """Return True if ``raw`` is one complete, checksum-valid LA frame of either direction.

    Checks the header (55 AA or AA 55), Len == total - 5 (A2-01) and the checksum.
    """
    raw = bytes(raw)
    if not MIN_FRAME_SIZE <= len(raw) <= MAX_FRAME_SIZE:
        return False
    if raw[:2] not in (LA_REQUEST_HEADER, LA_REPLY_HEADER):
        return False
    if raw[2] != len(raw) - FRAME_OVERHEAD:
        return False
    return raw[-1] == la_checksum(raw[:-1])


def _is_reply_frame(raw: bytes) -> bool:
    return raw[:2] == LA_REPLY_HEADER and frame_is_valid(raw)


def _u16(raw: bytes, at: int) -> int:
    return int.from_bytes(raw[at : at + 2], "little", signed=False)


def _s16(raw: bytes, at: int) -> int:
    return int.from_bytes(raw[at : at + 2], "little", signed=True)


def _check_id(value: object, *, allow_broadcast: bool) -> int:
    if allow_broadcast and value == BROADCAST_ID and not isinstance(value, bool):
        return BROADCAST_ID
    hint = f" or {BROADCAST_ID} (broadcast)" if allow_broadcast else " (broadcast not allowed)"
    try:
        return check_int("id", value, ID_MIN, ID_MAX)
    except LocalProtocolError as err:
        raise LocalProtocolError(f"{err}{hint}", field="id", value=value) from None


def _check_position(value: object) -> int:
    return check_int("position", value, POSITION_MIN, POSITION_MAX)


# --- enums -------------------------------------------------------------------------------------


class BaudCode(enum.IntEnum):
    """Baud-rate codes of control-table index 12 (doc 002 section 3.6; A2-13)."""

    B19200 = 0
    B57600 = 1
    B115200 = 2
    B921600 = 3

    @property
    def baud(self) -> int:
        """The bit rate in bit/s this code selects."""
        return _BAUD_RATES[self]


_BAUD_RATES = {
    BaudCode.B19200: 19200,
    BaudCode.B57600: 57600,
    BaudCode.B115200: 115200,
    BaudCode.B921600: 921600,
}


class ControlAction(enum.IntEnum):
    """CMD_MC (0x04) sub-commands, the SUB byte (doc 002 section 3.5.4)."""

    WORK = 0x04  # enable the power stage
    ESTOP = 0x23  # disable; WORK is needed before the next position command
    PAUSE = 0x14  # disable; the next position command resumes directly
    SAVE = 0x20  # copy the RAM control table to flash ("参数装订")
    QUERY_STATUS = 0x22  # status (BIT)
    CLEAR_FAULT = 0x1E  # clear over-current, stall, motor-abnormal (not over-temperature)


class BroadcastMode(enum.IntEnum):
    """The two broadcast commands (doc 002 section 3.5.3)."""

    POSITION = CMD_BROADCAST_MOVE
    FOLLOW = CMD_BROADCAST_FOLLOW


class ErrorFlags(enum.IntFlag, boundary=enum.KEEP):
    """Status byte B15 (doc 002 section 3.5.4); bits 4..7 are undefined and kept raw (A2-19)."""

    STALL = 0x01
    OVER_TEMPERATURE = 0x02
    OVER_CURRENT = 0x04
    MOTOR_ABNORMAL = 0x08


#: The defined fault bits; anything else in B15 is reported raw but not treated as a fault.
KNOWN_ERROR_BITS = (
    ErrorFlags.STALL
    | ErrorFlags.OVER_TEMPERATURE
    | ErrorFlags.OVER_CURRENT
    | ErrorFlags.MOTOR_ABNORMAL
)


#: An error byte with no bit set.
NO_ERRORS = ErrorFlags(0)
#: Every possible error byte as flags, built once (an IntFlag call costs ~0.5 us).
_ERROR_FLAGS = tuple(ErrorFlags(i) for i in range(256))


# --- the control table ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class RegisterInfo:
    """The layout of one documented control-table register (doc 002 section 3.6, C.5).

    ``minimum``/``maximum`` are the write range for writable registers and the nominal
    range of the reading for read-only ones.  ``default`` is the factory value, if any.
    """

    index: int
    size: int
    signed: bool
    minimum: int
    maximum: int
    writable: bool
    unit: str
    default: int | None


class Register(enum.Enum):
    """Every documented register of the LA control table (doc 002 section 3.6, C.5).

    Look up by name with ``Register["TARGET"]`` or ``Register.by_name("target")``, by index
    with ``Register.by_index(55)``.
    """

    _value_: RegisterInfo

    #: Actuator ID; takes effect at once, save to keep (3.6 index 2; A2-12).
    ID = RegisterInfo(2, 1, False, ID_MIN, ID_MAX, True, "", 1)
    #: Baud code (``BaudCode``); needs save and a power cycle (3.6 index 12; A2-13).
    BAUD = RegisterInfo(12, 1, False, 0, 3, True, "code", BaudCode.B921600)
    #: Current position, int16, -20..2020 (3.6 index 26).
    POSITION = RegisterInfo(
        26, 2, True, REPORTED_POSITION_MIN, REPORTED_POSITION_MAX, False, "", None
    )
    #: Force-sensor zero: write 1 to take the present reading as zero (3.6 index 31).
    FORCE_ZERO = RegisterInfo(31, 1, False, 1, 1, True, "", 0)
    #: Over-current limit, 300..1500 mA (3.6 index 32).
    OVER_CURRENT_LIMIT = RegisterInfo(32, 2, False, 300, 1500, True, "mA", 1500)
    #: Target position 0..2000; writing it also starts a move (3.6 index 55; A2-21).
    TARGET = RegisterInfo(TARGET_INDEX, 2, False, POSITION_MIN, POSITION_MAX, True, "", None)
    #: Force in grams, int16 (3.6 index 76; A2-07).
    FORCE = RegisterInfo(76, 2, True, -32768, 32767, False, "g", None)
    #: Raw force ADC, 12-bit so nominally 0..4095 (3.6 index 78; A2-07).
    RAW_FORCE = RegisterInfo(78, 2, False, 0, 4095, False, "counts", None)
    #: Over-temperature limit in 0.1 degC, [(recovery + 5) * 10, 800] (3.6 index 98; A2-14).
    OVER_TEMPERATURE_LIMIT = RegisterInfo(98, 2, False, 250, 800, True, "0.1 degC", 800)
    #: Recovery temperature in 0.1 degC, [200, (over-temp - 5) * 10] (3.6 index 100; A2-14).
    RECOVERY_TEMPERATURE = RegisterInfo(100, 2, False, 200, 750, True, "0.1 degC", 600)

    def __repr__(self) -> str:
        return f"Register.{self.name}"

    @property
    def index(self) -> int:
        """First control-table byte of the register."""
        return self.value.index

    @property
    def size(self) -> int:
        """Size in bytes (1 or 2)."""
        return self.value.size

    @property
    def signed(self) -> bool:
        """True if the register holds a two's-complement value."""
        return self.value.signed

    @property
    def minimum(self) -> int:
        """Lowest allowed write value (read-only registers: lowest nominal reading)."""
        return self.value.minimum

    @property
    def maximum(self) -> int:
        """Highest allowed write value (read-only registers: highest nominal reading)."""
        return self.value.maximum

    @property
    def writable(self) -> bool:
        """True if the host may write the register."""
        return self.value.writable

    @property
    def field_name(self) -> str:
        """The name used in error messages, e.g. ``over_current_limit``."""
        return self.name.lower()

    @classmethod
    def by_name(cls, name: str) -> Register:
        """Return the register called ``name`` (case-insensitive).

        Raises:
            LocalProtocolError: no register has that name.
        """
        try:
            return cls[name.upper()]
        except KeyError:
            names = ", ".join(r.name for r in cls)
            raise LocalProtocolError(
                f"register={name!r} is not allowed: choose one of {names}",
                field="register",
                value=name,
            ) from None

    @classmethod
    def by_index(cls, index: int) -> Register:
        """Return the register that starts at control-table ``index``.

        Raises:
            LocalProtocolError: no documented register starts there.
        """
        for reg in cls:
            if reg.index == index:
                return reg
        indices = ", ".join(str(r.index) for r in cls)
        raise LocalProtocolError(
            f"index={index!r} is not allowed: registers start at {indices}",
            field="index",
            value=index,
        )

    @classmethod
    def at(cls, index: int, size: int) -> Register | None:
        """Return the register exactly covering ``size`` bytes at ``index``, else ``None``."""
        for reg in cls:
            if reg.index == index and reg.size == size:
                return reg
        return None

    def check_value(self, value: object) -> int:
        """Return ``value`` if it may be written to this register.

        Raises:
            LocalProtocolError: the register is read-only, or the value is out of range.
        """
        if not self.writable:
            raise LocalProtocolError(
                f"register {self.name} (index {self.index}) is read-only",
                field="register",
                value=self,
            )
        return check_int(self.field_name, value, self.minimum, self.maximum)

    def encode_value(self, value: int) -> bytes:
        """Return the little-endian bytes of ``value`` in this register's size and sign.

        Raises:
            LocalProtocolError: ``value`` does not fit the register's size and sign.
        """
        bits = 8 * self.size
        lo, hi = (
            (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if self.signed else (0, (1 << bits) - 1)
        )
        check_int(self.field_name, value, lo, hi)
        return value.to_bytes(self.size, "little", signed=self.signed)

    def decode_value(self, data: bytes) -> int:
        """Decode the register's little-endian bytes (``len(data)`` must equal ``size``).

        Raises:
            RemoteProtocolError: wrong number of bytes.
        """
        if len(data) != self.size:
            raise RemoteProtocolError(
                f"register {self.name} needs {self.size} bytes, got {len(data)}", raw=bytes(data)
            )
        return int.from_bytes(data, "little", signed=self.signed)


# --- replies -------------------------------------------------------------------------------------


class _StatusFields(NamedTuple):
    id: int
    target: int
    position: int
    temperature: int = 25
    current: int = 0
    force: int = 0
    errors: ErrorFlags = NO_ERRORS
    cmd_echo: int = CMD_CONTROL
    param1: int = 0x00
    param2: int = ControlAction.QUERY_STATUS
    internal1: int = 0
    internal2: int = 0


class Status(_StatusFields):
    """The 22-byte status frame (doc 002 section 3.5.4, docs/protocols.md C.4).

    Attributes:
        id: actuator ID (B3).
        cmd_echo: B4, 0x04 or the request's CMD (A2-04).
        param1: B5 (00 in the manual, V6).
        param2: B6 (0x22 in the manual's table; not checked).
        target: target position, uint16 (B7-B8).
        position: current position, int16, nominally -20..2020 (B9-B10).
        temperature: whole degC, int8 (B11).
        current: motor current in mA: int16 (B12-B13) made absolute (A2-06).
        force: grams, int16 of B14 (low) and B16 (high) around the error byte (A2-05).
        errors: B15 fault flags; undefined bits are kept (A2-19).
        internal1, internal2: uint16 (B17-B18, B19-B20).

    An immutable NamedTuple rather than a frozen dataclass: the bus decodes one per
    reply and streams poll hundreds a second, and ``decode_status`` builds it from
    struct-unpacked fields (whose ranges the struct types already guarantee) without
    re-validating, about 8x faster.  Constructing one by hand validates every field.
    """

    __slots__ = ()

    def __new__(
        cls,
        id: int,
        target: int,
        position: int,
        temperature: int = 25,
        current: int = 0,
        force: int = 0,
        errors: ErrorFlags | int = NO_ERRORS,
        cmd_echo: int = CMD_CONTROL,
        param1: int = 0x00,
        param2: int = ControlAction.QUERY_STATUS,
        internal1: int = 0,
        internal2: int = 0,
    ) -> Status:
        check_int("id", id, 0, 0xFF)
        check_int("cmd_echo", cmd_echo, 0, 0xFF)
        check_int("param1", param1, 0, 0xFF)
        check_int("param2", param2, 0, 0xFF)
        check_int("target", target, 0, 0xFFFF)
        check_int("position", position, -0x8000, 0x7FFF)
        check_int("temperature", temperature, -0x80, 0x7F)
        # 32768 is the abs() of int16 -32768, which the decoder can produce.
        check_int("current", current, 0, 0x8000)
        check_int("force", force, -0x8000, 0x7FFF)
        check_int("errors", int(errors), 0, 0xFF)
        check_int("internal1", internal1, 0, 0xFFFF)
        check_int("internal2", internal2, 0, 0xFFFF)
        flags = _ERROR_FLAGS[int(errors)]
        return super().__new__(
            cls,
            id,
            target,
            position,
            temperature,
            current,
            force,
            flags,
            cmd_echo,
            param1,
            param2,
            internal1,
            internal2,
        )

    @property
    def fault(self) -> bool:
        """True if any defined fault bit (stall, over-temperature, over-current, motor
        abnormal) is set.  Undefined bits 4..7 alone do not count (A2-19)."""
        return bool(self.errors & KNOWN_ERROR_BITS)

    def encode(self) -> bytes:
        """Return the 22-byte reply frame ``AA 55 11 ...`` (used by the simulator)."""
        force = self.force.to_bytes(2, "little", signed=True)
        body = (
            bytes((self.id, self.cmd_echo, self.param1, self.param2))
            + self.target.to_bytes(2, "little")
            + self.position.to_bytes(2, "little", signed=True)
            + self.temperature.to_bytes(1, "little", signed=True)
            + self.current.to_bytes(2, "little")
            + bytes((force[0], int(self.errors), force[1]))
            + self.internal1.to_bytes(2, "little")
            + self.internal2.to_bytes(2, "little")
        )
        return build_frame(LA_REPLY_HEADER, body)

    @classmethod
    def decode(cls, raw: bytes) -> Status:
        """Decode a 22-byte status frame (any B4).

        Raises:
            RemoteProtocolError: not a valid status frame.
        """
        return decode_status(raw)


def encode_status(
    id: int,
    *,
    target: int,
    position: int,
    temperature: int = 25,
    current: int = 0,
    force: int = 0,
    errors: int = 0,
    cmd_echo: int = CMD_CONTROL,
    param1: int = 0x00,
    param2: int = ControlAction.QUERY_STATUS,
    internal1: int = 0,
    internal2: int = 0,
) -> bytes:
    """Build a 22-byte status frame from its fields (see ``Status`` for units).

    Raises:
        LocalProtocolError: a field does not fit its byte(s).
    """
    return Status(
        id=id,
        target=target,
        position=position,
        temperature=temperature,
        current=current,
        force=force,
        errors=ErrorFlags(check_int("errors", errors, 0, 0xFF)),
        cmd_echo=cmd_echo,
        param1=param1,
        param2=param2,
        internal1=internal1,
        internal2=internal2,
    ).encode()


def _is_status_frame(raw: bytes) -> bool:
    return len(raw) == STATUS_FRAME_SIZE and raw[2] == STATUS_LEN_BYTE and _is_reply_frame(raw)


def decode_status(raw: bytes, *, checked: bool = False) -> Status:
    """Decode a 22-byte status frame; B4 and B6 are recorded, not checked (A2-04).

    Args:
        raw: the frame.
        checked: the caller has already verified header, Len and checksum (the
            reassembler and ``matches_reply`` do), so they are not verified again.

    Raises:
        RemoteProtocolError: wrong size, Len, header or checksum.
    """
    if not checked and not _is_status_frame(raw):
        raise RemoteProtocolError(f"{format_hex(raw)} is not an LA status frame", raw=bytes(raw))
    ident, cmd, p1, p2, target, position, temp, current, f_lo, err, f_hi, in1, in2 = (
        _STATUS_LAYOUT.unpack_from(raw, 3)
    )
    force = f_lo | f_hi << 8
    if force & 0x8000:
        force -= 0x10000
    return _make_status(
        (
            ident,
            target,
            position,
            temp,
            abs(current),
            force,
            _ERROR_FLAGS[err],
            cmd,
            p1,
            p2,
            in1,
            in2,
        )
    )


#: B3..B20 of the status frame: ID, CMD, param1, param2, target (u16), position (s16),
#: temperature (s8), current (s16), force low, error flags, force high, internal 1, 2.
_STATUS_LAYOUT = struct.Struct("<4BHhbhBBBHH")
#: Builds a Status from decoded fields without re-validating them (see ``Status``).
_make_status = Status._make


@dataclass(frozen=True, slots=True)
class ReadReply:
    """Reply to CMD_RD: ``AA 55 (N+2) ID 01 IDX d1..dN CS`` (doc 002 section 3.4.1)."""

    id: int
    index: int
    data: bytes


@dataclass(frozen=True, slots=True)
class WriteAck:
    """The short write ack ``AA 55 03 ID 02 IDX 00 CS`` (doc 002 section 3.4.1, A2-03)."""

    id: int
    index: int
    reserved: int


@dataclass(frozen=True, slots=True)
class UnknownReply:
    """A valid reply frame of no known shape: kept whole for logging and diagnosis."""

    id: int
    cmd: int
    payload: bytes
    raw: bytes


def decode_reply(raw: bytes) -> Status | ReadReply | WriteAck | UnknownReply:
    """Decode any valid LA reply frame without knowing the request.

    Read replies are recognised by CMD 0x01, short write acks by Len 3 and CMD 0x02, status
    frames by Len 0x11 (any B4, A2-04); anything else valid is an ``UnknownReply``.

    Raises:
        RemoteProtocolError: not a complete, checksum-valid ``AA 55`` frame.
    """
    raw = bytes(raw)
    if not _is_reply_frame(raw):
        raise RemoteProtocolError(f"{format_hex(raw)} is not a valid LA reply frame", raw=raw)
    length, cmd = raw[2], raw[4]
    if cmd == CMD_READ and length >= 3:
        return ReadReply(id=raw[3], index=raw[5], data=raw[6:-1])
    if cmd == CMD_WRITE and length == WRITE_ACK_LEN_BYTE:
        return WriteAck(id=raw[3], index=raw[5], reserved=raw[6])
    if length == STATUS_LEN_BYTE:
        return decode_status(raw)
    return UnknownReply(id=raw[3], cmd=cmd, payload=raw[5:-1], raw=raw)


# --- commands ------------------------------------------------------------------------------


class LACommand(Command[ReplyT_co]):
    """Common behaviour of LA requests (addressing, status matching)."""

    __slots__ = ()

    family: ClassVar[Family] = Family.LA

    def _status_ids(self) -> tuple[int, ...]:
        """IDs a reply to this request may carry."""
        raise NotImplementedError

    def _matches_status(self, raw: bytes, request_cmd: int) -> bool:
        return (
            _is_status_frame(raw)
            and raw[3] in self._status_ids()
            and raw[4] in (CMD_CONTROL, request_cmd)
        )

    @property
    def device_key(self) -> str:
        """``"la:ID"`` (``"la:255"`` for a broadcast)."""
        return f"la:{getattr(self, 'id', BROADCAST_ID)}"

    def fault_state(self, reply: object) -> FaultState | None:
        """The error flags (B15) of a status reply; ``None`` for other replies."""
        if isinstance(reply, Status):
            return FaultState(reply.id, int(reply.errors))
        return None

    def _decode_checked_status(self, raw: bytes) -> Status:
        if not self.matches_reply(raw):
            raise RemoteProtocolError(
                f"{format_hex(raw)} is not a reply to {type(self).__name__}", raw=raw
            )
        return decode_status(raw)


@dataclass(frozen=True, slots=True)
class ReadTable(LACommand[ReadReply]):
    """CMD_RD 0x01: read ``count`` control-table bytes from ``index`` (doc 002 section 3.5.1).

    Args:
        id: actuator ID 1..254 (a broadcast read could not be answered).
        index: first byte, 0..254.
        count: number of bytes, 1..min(253, 255 - index).
    """

    id: int
    index: int
    count: int

    def __post_init__(self) -> None:
        _check_id(self.id, allow_broadcast=False)
        check_int("index", self.index, 0, TABLE_INDEX_MAX)
        check_int("count", self.count, 1, min(MAX_TABLE_BYTES, TABLE_SIZE - self.index))

    def encode(self) -> bytes:
        """Return ``55 AA 03 ID 01 IDX N CS``."""
        return build_frame(LA_REQUEST_HEADER, bytes((self.id, CMD_READ, self.index, self.count)))

    def reply_lengths(self) -> tuple[int, ...]:
        """The reply is ``count + 7`` bytes."""
        return (self.count + FRAME_OVERHEAD + 2,)

    def _status_ids(self) -> tuple[int, ...]:
        return (self.id,)

    def matches_reply(self, raw: bytes) -> bool:
        """True for a valid read reply from this ID echoing the index with ``count`` bytes."""
        raw = bytes(raw)
        return (
            len(raw) == self.count + FRAME_OVERHEAD + 2
            and _is_reply_frame(raw)
            and raw[3] == self.id
            and raw[4] == CMD_READ
            and raw[5] == self.index
        )

    def decode_reply(self, raw: bytes) -> ReadReply:
        """Decode the reply into a ``ReadReply``.

        Raises:
            RemoteProtocolError: ``raw`` is not a reply to this request.
        """
        raw = bytes(raw)
        if not self.matches_reply(raw):
            raise RemoteProtocolError(f"{format_hex(raw)} is not a reply to {self!r}", raw=raw)
        return ReadReply(id=raw[3], index=raw[5], data=raw[6:-1])


@dataclass(frozen=True, slots=True)
class ReadRegister(LACommand[int]):
    """Typed read of one documented register; the reply decodes to its integer value.

    Args:
        id: actuator ID 1..254.
        register: which register (``Register``).
    """

    id: int
    # field() because ``register`` would otherwise pick up ABCMeta.register as a default.
    register: Register = field()

    def __post_init__(self) -> None:
        _check_id(self.id, allow_broadcast=False)
        if not isinstance(self.register, Register):
            raise LocalProtocolError(
                f"register={self.register!r} is not a Register", field="register"
            )

    @property
    def as_table(self) -> ReadTable:
        """The equivalent raw ``ReadTable``."""
        return ReadTable(self.id, self.register.index, self.register.size)

    def encode(self) -> bytes:
        """Return ``55 AA 03 ID 01 IDX size CS``."""
        return self.as_table.encode()

    def reply_lengths(self) -> tuple[int, ...]:
        """The reply is ``size + 7`` bytes."""
        return self.as_table.reply_lengths()

    def matches_reply(self, raw: bytes) -> bool:
        """True for a read reply from this ID and index with the register's size."""
        return self.as_table.matches_reply(raw)

    def decode_reply(self, raw: bytes) -> int:
        """Return the register value (signed for int16 registers).

        Raises:
            RemoteProtocolError: ``raw`` is not a reply to this request.
        """
        return self.register.decode_value(self.as_table.decode_reply(raw).data)


@dataclass(frozen=True, slots=True)
class WriteTable(LACommand[Status | WriteAck]):
    """CMD_WR 0x02: write raw bytes into the control table (doc 002 section 3.5.2).

    The reply is the 22-byte status frame or the short ack (A2-03).  If the write covers
    the ID byte the reply may come from the old or the new ID (A2-12).  A write covering
    the target register starts a move (A2-21).

    Args:
        id: actuator ID 1..254, or 255 to write every actuator (no reply).
        index: first byte, 0..254.
        data: 1..min(253, 255 - index) bytes, little-endian for multi-byte fields.
    """

    id: int
    index: int
    data: bytes

    def __post_init__(self) -> None:
        _check_id(self.id, allow_broadcast=True)
        check_int("index", self.index, 0, TABLE_INDEX_MAX)
        if not isinstance(self.data, bytes | bytearray):
            raise LocalProtocolError(
                f"data must be bytes, got {type(self.data).__name__}", field="data"
            )
        object.__setattr__(self, "data", bytes(self.data))
        check_int("len(data)", len(self.data), 1, min(MAX_TABLE_BYTES, TABLE_SIZE - self.index))

    def _covers(self, index: int) -> bool:
        return self.index <= index < self.index + len(self.data)

    @property
    def starts_motion(self) -> bool:  # type: ignore[override]
        """True if the write covers the target register: the actuator moves (A2-21)."""
        return self._covers(TARGET_INDEX)

    def encode(self) -> bytes:
        """Return ``55 AA (N+2) ID 02 IDX d1..dN CS``."""
        return build_frame(LA_REQUEST_HEADER, bytes((self.id, CMD_WRITE, self.index)) + self.data)

    def reply_lengths(self) -> tuple[int, ...]:
        """Status frame or short ack; nothing for a broadcast."""
        if self.id == BROADCAST_ID:
            return ()
        return (STATUS_FRAME_SIZE, WRITE_ACK_FRAME_SIZE)

    def _status_ids(self) -> tuple[int, ...]:
        register_index = Register.ID.index
        if self._covers(register_index):
            return (self.id, self.data[register_index - self.index])
        return (self.id,)

    def matches_reply(self, raw: bytes) -> bool:
        """True for a status frame or a short ack (echoing the index) from an accepted ID."""
        raw = bytes(raw)
        if self.id == BROADCAST_ID:
            return False
        if self._matches_status(raw, CMD_WRITE):
            return True
        return (
            len(raw) == WRITE_ACK_FRAME_SIZE
            and _is_reply_frame(raw)
            and raw[3] in self._status_ids()
            and raw[4] == CMD_WRITE
            and raw[5] == self.index
        )

    def decode_reply(self, raw: bytes) -> Status | WriteAck:
        """Decode the reply into a ``Status`` or a ``WriteAck``.

        Raises:
            RemoteProtocolError: ``raw`` is not a reply to this request.
        """
        raw = bytes(raw)
        if not self.matches_reply(raw):
            raise RemoteProtocolError(f"{format_hex(raw)} is not a reply to {self!r}", raw=raw)
        if len(raw) == STATUS_FRAME_SIZE:
            return decode_status(raw)
        return WriteAck(id=raw[3], index=raw[5], reserved=raw[6])


@dataclass(frozen=True, slots=True)
class WriteRegister(LACommand[Status | WriteAck]):
    """Typed write of one documented, writable register (refuses read-only ones).

    Writing ``Register.TARGET`` also moves the actuator (A2-21); prefer ``MoveTo``.

    Args:
        id: actuator ID 1..254, or 255 (every actuator, no reply).
        register: which register.
        value: the value in the register's unit, within its write range.
    """

    id: int
    # field() because ``register`` would otherwise pick up ABCMeta.register as a default.
    register: Register = field()
    value: int

    def __post_init__(self) -> None:
        _check_id(self.id, allow_broadcast=True)
        if not isinstance(self.register, Register):
            raise LocalProtocolError(
                f"register={self.register!r} is not a Register", field="register"
            )
        self.register.check_value(self.value)

    @property
    def starts_motion(self) -> bool:  # type: ignore[override]
        """True for a write of the target register: the actuator moves (A2-21)."""
        return self.register is Register.TARGET

    @property
    def as_table(self) -> WriteTable:
        """The equivalent raw ``WriteTable``."""
        return WriteTable(self.id, self.register.index, self.register.encode_value(self.value))

    def encode(self) -> bytes:
        """Return ``55 AA (size+2) ID 02 IDX value.. CS``."""
        return self.as_table.encode()

    def reply_lengths(self) -> tuple[int, ...]:
        """Status frame or short ack; nothing for a broadcast."""
        return self.as_table.reply_lengths()

    def matches_reply(self, raw: bytes) -> bool:
        """True for a status frame or short ack from the ID (old or new for an ID write)."""
        return self.as_table.matches_reply(raw)

    def decode_reply(self, raw: bytes) -> Status | WriteAck:
        """Decode the reply into a ``Status`` or a ``WriteAck``.

        Raises:
            RemoteProtocolError: ``raw`` is not a reply to this request.
        """
        return self.as_table.decode_reply(raw)


class _TargetCommand(LACommand[Status]):
    """Shared code of MoveTo and Follow: ``55 AA 04 ID CMD 37 PosL PosH CS``."""

    __slots__ = ()

    starts_motion: ClassVar[bool] = True
    _cmd_reply: ClassVar[int]
    _cmd_silent: ClassVar[int]

    # Provided by the dataclass subclasses.
    id: int
    position: int
    reply: bool

    def _validate(self) -> None:
        _check_id(self.id, allow_broadcast=True)
        _check_position(self.position)
        if not isinstance(self.reply, bool):
            raise LocalProtocolError(
                f"reply must be True or False, got {self.reply!r}", field="reply", value=self.reply
            )

    @property
    def cmd(self) -> int:
        """The command code: with or without a status reply."""
        return self._cmd_reply if self.reply else self._cmd_silent

    def encode(self) -> bytes:
        """Return ``55 AA 04 ID CMD 37 PosL PosH CS``."""
        body = bytes((self.id, self.cmd, TARGET_INDEX)) + self.position.to_bytes(2, "little")
        return build_frame(LA_REQUEST_HEADER, body)

    def reply_lengths(self) -> tuple[int, ...]:
        """One status frame, or nothing for the no-reply variant and for ID 255."""
        if not self.reply or self.id == BROADCAST_ID:
            return ()
        return (STATUS_FRAME_SIZE,)

    def _status_ids(self) -> tuple[int, ...]:
        return (self.id,)

    def matches_reply(self, raw: bytes) -> bool:
        """True for a status frame from this ID with B4 = 0x04 or this CMD (A2-04)."""
        return bool(self.reply_lengths()) and self._matches_status(bytes(raw), self.cmd)

    def decode_reply(self, raw: bytes) -> Status:
        """Decode the status reply.

        Raises:
            RemoteProtocolError: ``raw`` is not a reply to this request.
        """
        return self._decode_checked_status(bytes(raw))


@dataclass(frozen=True, slots=True)
class MoveTo(_TargetCommand):
    """Positioning: a planned, shortest-time move (0x21 with reply, 0x03 without; 3.5.3).

    Args:
        id: actuator ID 1..254, or 255 for every actuator (no reply).
        position: target 0..2000 (0..100 % of stroke).
        reply: ask for the status reply (0x21) or not (0x03).
    """

    _cmd_reply: ClassVar[int] = CMD_MOVE
    _cmd_silent: ClassVar[int] = CMD_MOVE_NO_REPLY

    id: int
    position: int
    reply: bool = True

    def __post_init__(self) -> None:
        self._validate()


@dataclass(frozen=True, slots=True)
class Follow(_TargetCommand):
    """Follow (servo) mode: track streamed targets (0x20 with reply, 0x19 without; 3.5.3).

    Send at a fixed interval of 10..50 ms (doc 002 section 3.5.3; A2-15).

    Args:
        id: actuator ID 1..254, or 255 for every actuator (no reply).
        position: target 0..2000.
        reply: ask for the status reply (0x20) or not (0x19).
    """

    _cmd_reply: ClassVar[int] = CMD_FOLLOW
    _cmd_silent: ClassVar[int] = CMD_FOLLOW_NO_REPLY

    id: int
    position: int
    reply: bool = True

    def __post_init__(self) -> None:
        self._validate()


@dataclass(frozen=True, slots=True)
class Control(LACommand[Status]):
    """CMD_MC 0x04 single control: ``55 AA 03 ID 04 00 SUB CS`` (doc 002 section 3.5.4).

    Args:
        id: actuator ID 1..254, or 255 for every actuator (no reply).
        action: the ``ControlAction`` sub-command.
    """

    id: int
    action: ControlAction

    def __post_init__(self) -> None:
        _check_id(self.id, allow_broadcast=True)
        check_choice("action", self.action, [int(a) for a in ControlAction], "CMD_MC sub-command")
        object.__setattr__(self, "action", ControlAction(self.action))

    def encode(self) -> bytes:
        """Return ``55 AA 03 ID 04 00 SUB CS``."""
        body = bytes((self.id, CMD_CONTROL, CONTROL_RESERVED, self.action))
        return build_frame(LA_REQUEST_HEADER, body)

    def reply_lengths(self) -> tuple[int, ...]:
        """One status frame, or nothing for ID 255."""
        return () if self.id == BROADCAST_ID else (STATUS_FRAME_SIZE,)

    def _status_ids(self) -> tuple[int, ...]:
        return (self.id,)

    def matches_reply(self, raw: bytes) -> bool:
        """True for a status frame from this ID."""
        return bool(self.reply_lengths()) and self._matches_status(bytes(raw), CMD_CONTROL)

    def decode_reply(self, raw: bytes) -> Status:
        """Decode the status reply.

        Raises:
            RemoteProtocolError: ``raw`` is not a reply to this request.
        """
        return self._decode_checked_status(bytes(raw))


@dataclass(frozen=True, slots=True)
class Broadcast(LACommand[None]):
    """Broadcast positioning (0xF2) or follow (0xF3) for up to 15 actuators (3.5.3, C.8).

    ``55 AA (1+3N) FF F2|F3 {ID PosL PosH} x N CS``; nothing replies.

    Args:
        mode: ``BroadcastMode.POSITION`` or ``BroadcastMode.FOLLOW``.
        entries: 1..15 pairs ``(id 1..254, position 0..2000)`` with distinct IDs.
    """

    mode: BroadcastMode
    entries: tuple[tuple[int, int], ...]

    def __post_init__(self) -> None:
        check_choice("mode", self.mode, [int(m) for m in BroadcastMode], "F2 position, F3 follow")
        object.__setattr__(self, "mode", BroadcastMode(self.mode))
        try:
            entries = tuple((ident, pos) for ident, pos in self.entries)
        except (TypeError, ValueError):
            raise LocalProtocolError(
                f"entries must be (id, position) pairs, got {self.entries!r}", field="entries"
            ) from None
        check_int("len(entries)", len(entries), 1, MAX_BROADCAST_ENTRIES)
        seen: set[int] = set()
        # The checks return plain ints: numpy integers are stored as ints too.
        entries = tuple(
            (_check_id(ident, allow_broadcast=False), _check_position(pos))
            for ident, pos in entries
        )
        for ident, _pos in entries:
            if ident in seen:
                raise LocalProtocolError(
                    f"id={ident} appears twice in one broadcast: each actuator once",
                    field="id",
                    value=ident,
                )
            seen.add(ident)
        object.__setattr__(self, "entries", entries)

    @classmethod
    def prevalidated(cls, mode: BroadcastMode, entries: tuple[tuple[int, int], ...]) -> Broadcast:
        """Build without re-checking, for callers that already validated every ID and
        position and keep IDs distinct (the Streamer does, once per stream and target).
        It saves ~30 range checks per frame on the 100 Hz path; anything else should
        use the validating constructor."""
        obj = object.__new__(cls)
        object.__setattr__(obj, "mode", mode)
        object.__setattr__(obj, "entries", entries)
        return obj

    @property
    def starts_motion(self) -> bool:  # type: ignore[override]
        """Always True: every addressed actuator moves."""
        return True

    @property
    def id(self) -> int:
        """Always 255: the frame goes to every actuator."""
        return BROADCAST_ID

    def encode(self) -> bytes:
        """Return ``55 AA (1+3N) FF F2|F3 {ID PosL PosH}... CS``."""
        # Streams encode one of these per tick and bus: one bytes() call, no loop.
        body = bytes(
            (
                BROADCAST_ID,
                self.mode,
                *(b for ident, pos in self.entries for b in (ident, pos & 0xFF, pos >> 8)),
            )
        )
        return build_frame(LA_REQUEST_HEADER, body)

    def reply_lengths(self) -> tuple[int, ...]:
        """``()``: nothing answers a broadcast."""
        return ()

    def _status_ids(self) -> tuple[int, ...]:
        return ()

    def matches_reply(self, raw: bytes) -> bool:
        """Always False: nothing answers a broadcast."""
        return False

    def decode_reply(self, raw: bytes) -> None:
        """Never valid: a broadcast has no reply.

        Raises:
            RemoteProtocolError: always.
        """
        raise RemoteProtocolError(f"{format_hex(raw)}: a broadcast has no reply", raw=bytes(raw))


def split_broadcast(
    mode: BroadcastMode, targets: Mapping[int, int] | Iterable[tuple[int, int]]
) -> list[Broadcast]:
    """Split targets for many actuators into broadcast frames of at most 15 entries (C.8).

    Args:
        mode: ``BroadcastMode.POSITION`` or ``BroadcastMode.FOLLOW``.
        targets: ``{id: position}`` or ``(id, position)`` pairs; order is kept.

    Returns:
        The frames to send back-to-back (empty if there are no targets).

    Raises:
        LocalProtocolError: an ID or position out of range, or an ID given twice.
    """
    pairs = list(targets.items()) if isinstance(targets, Mapping) else list(targets)
    seen: set[object] = set()
    for ident, _ in pairs:
        if ident in seen:
            raise LocalProtocolError(
                f"id={ident} appears twice in the broadcast targets", field="id", value=ident
            )
        seen.add(ident)
    return [
        Broadcast(mode, tuple(pairs[i : i + MAX_BROADCAST_ENTRIES]))
        for i in range(0, len(pairs), MAX_BROADCAST_ENTRIES)
    ]


# --- request decoding (simulator, ``motorbus decode``) -----------------------------------------


def _decode_request_body(raw: bytes) -> LACommand[object]:
    length, ident, cmd = raw[2], raw[3], raw[4]
    if cmd in (CMD_BROADCAST_MOVE, CMD_BROADCAST_FOLLOW):
        if ident != BROADCAST_ID:
            raise LocalProtocolError(f"broadcast frame with id={ident}, expected 255", field="id")
        if (length - 1) % BROADCAST_ENTRY_SIZE:
            raise LocalProtocolError(f"broadcast Len={length} is not 1 + 3N", field="Len")
        payload = raw[5:-1]
        entries = tuple(
            (payload[i], int.from_bytes(payload[i + 1 : i + 3], "little"))
            for i in range(0, len(payload), BROADCAST_ENTRY_SIZE)
        )
        return Broadcast(BroadcastMode(cmd), entries)
    if length < 2:
        raise LocalProtocolError(f"Len={length} leaves no IDX byte", field="Len")
    index, data = raw[5], raw[6:-1]
    if cmd == CMD_READ:
        check_int("Len", length, READ_REQUEST_LEN_BYTE, READ_REQUEST_LEN_BYTE)
        reg = Register.at(index, data[0])
        if reg is not None:
            return ReadRegister(ident, reg)
        return ReadTable(ident, index, data[0])
    if cmd == CMD_WRITE:
        reg = Register.at(index, len(data))
        if reg is not None and reg.writable:
            value = int.from_bytes(data, "little", signed=reg.signed)
            try:
                return WriteRegister(ident, reg, value)
            except LocalProtocolError:
                pass  # out of the documented range: still a valid raw write
        return WriteTable(ident, index, data)
    if cmd in (CMD_MOVE, CMD_MOVE_NO_REPLY, CMD_FOLLOW, CMD_FOLLOW_NO_REPLY):
        check_int("Len", length, MOTION_LEN_BYTE, MOTION_LEN_BYTE)
        check_choice("IDX", index, [TARGET_INDEX], "motion frames address the target register")
        position = int.from_bytes(data, "little")
        kind = MoveTo if cmd in (CMD_MOVE, CMD_MOVE_NO_REPLY) else Follow
        return kind(ident, position, reply=cmd in (CMD_MOVE, CMD_FOLLOW))
    if cmd == CMD_CONTROL:
        # The IDX byte is reserved (send 00, V6); a device ignores it, so do we.
        check_int("Len", length, CONTROL_LEN_BYTE, CONTROL_LEN_BYTE)
        return Control(ident, ControlAction(check_choice("sub", data[0], list(ControlAction))))
    raise LocalProtocolError(f"cmd=0x{cmd:02X} is not an LA request command", field="cmd")


def decode_request(raw: bytes) -> Command[object]:
    """Decode a request frame (``55 AA ...``) back into its ``Command`` value.

    A write whose index and size match a writable register, with a value in its range,
    comes back as ``WriteRegister`` (likewise reads as ``ReadRegister``); other writes and
    reads as ``WriteTable``/``ReadTable``.

    Raises:
        RemoteProtocolError: not a valid request frame, or fields no request can carry;
            the error carries ``raw``.
    """
    raw = bytes(raw)
    if raw[:2] != LA_REQUEST_HEADER or not frame_is_valid(raw):
        raise RemoteProtocolError(f"{format_hex(raw)} is not a valid LA request frame", raw=raw)
    try:
        return _decode_request_body(raw)
    except LocalProtocolError as err:
        raise RemoteProtocolError(f"{format_hex(raw)}: {err}", raw=raw) from err


# --- temperature limits (A2-14) ---------------------------------------------------------------


def temperature_limit_writes(
    id: int,
    over_c10: int,
    recovery_c10: int,
    current_over_c10: int,
    current_recovery_c10: int,
) -> list[WriteRegister]:
    """Plan the writes that set both temperature limits without an invalid intermediate state.

    The actuator requires over-temperature >= recovery + 5 degC (doc 002 section 3.6; A2-14).
    Raising, write the over-temperature limit first; lowering, the recovery temperature first.
    If the present pair is itself invalid and neither order works, recovery is first set to
    its minimum (20.0 degC).  Unchanged values are not written.

    Args:
        id: actuator ID 1..254 (or 255).
        over_c10: new over-temperature limit, 0.1 degC, 250..800.
        recovery_c10: new recovery temperature, 0.1 degC, 200..750.
        current_over_c10: the limit the actuator holds now (e.g. read from index 98).
        current_recovery_c10: the recovery temperature it holds now (index 100).

    Returns:
        The ``WriteRegister`` commands in the order to send them.

    Raises:
        LocalProtocolError: a value out of range, or ``over_c10 < recovery_c10 + 50``.
    """
    over_reg, rec_reg = Register.OVER_TEMPERATURE_LIMIT, Register.RECOVERY_TEMPERATURE
    over_reg.check_value(over_c10)
    rec_reg.check_value(recovery_c10)
    check_int("current_over_c10", current_over_c10, over_reg.minimum, over_reg.maximum)
    check_int("current_recovery_c10", current_recovery_c10, rec_reg.minimum, rec_reg.maximum)
    if over_c10 < recovery_c10 + TEMPERATURE_GAP_C10:
        raise LocalProtocolError(
            f"over_c10={over_c10} and recovery_c10={recovery_c10} violate "
            f"over_c10 >= recovery_c10 + {TEMPERATURE_GAP_C10} (0.1 degC units)",
            field="over_c10",
            value=(over_c10, recovery_c10),
        )

    def valid(over: int, rec: int) -> bool:
        return over >= rec + TEMPERATURE_GAP_C10

    write_over = WriteRegister(id, over_reg, over_c10)
    write_rec = WriteRegister(id, rec_reg, recovery_c10)
    if over_c10 == current_over_c10 and recovery_c10 == current_recovery_c10:
        return []
    if over_c10 == current_over_c10:
        return [write_rec]
    if recovery_c10 == current_recovery_c10:
        return [write_over]
    if valid(over_c10, current_recovery_c10):
        return [write_over, write_rec]
    if valid(current_over_c10, recovery_c10):
        return [write_rec, write_over]
    return [WriteRegister(id, rec_reg, rec_reg.minimum), write_over, write_rec]
