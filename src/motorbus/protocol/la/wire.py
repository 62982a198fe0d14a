"""LA frame layout, IDs and values, command codes, frame helpers and enums (doc 002 3.3-3.5)."""

from __future__ import annotations

import enum

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import LA_REPLY_HEADER, LA_REQUEST_HEADER, check_int, format_hex, sum8
from motorbus.protocol.families import LA_BROADCAST_ID, LA_ID_MAX, LA_ID_MIN

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
    size = len(body)
    length = size - 1  # Len counts CMD .. last data byte: the body minus its ID byte
    check_int("body length", size, 2, 0xFF + 1)
    body = bytes(body)
    checksum = (length + sum(body)) & 0xFF  # la_checksum, inline: Len + ID .. DN
    return header + bytes((length,)) + body + bytes((checksum,))


def frame_is_valid(raw: bytes | bytearray | memoryview) -> bool:
    """Return True if ``raw`` is one complete, checksum-valid LA frame of either direction.

    Checks the header (55 AA or AA 55), Len == total - 5 (A2-01) and the checksum.
    """
    raw = bytes(raw)
    size = len(raw)
    if not MIN_FRAME_SIZE <= size <= MAX_FRAME_SIZE:
        return False
    if raw[:2] not in (LA_REQUEST_HEADER, LA_REPLY_HEADER):
        return False
    if raw[2] != size - FRAME_OVERHEAD:
        return False
    # la_checksum, inline: the bus checks every reply it matches (issue 40 counts calls).
    return raw[-1] == sum(raw[2:-1]) & 0xFF


def _is_reply_frame(raw: bytes) -> bool:
    return raw[:2] == LA_REPLY_HEADER and frame_is_valid(raw)


def _u16(raw: bytes, at: int) -> int:
    return int.from_bytes(raw[at : at + 2], "little", signed=False)


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

    def __repr__(self) -> str:
        """``ErrorFlags(none)``, ``ErrorFlags(STALL|OVER_CURRENT)``; undefined bits in hex."""
        value = int(self)
        names = [f.name for f in ErrorFlags if f.name and value & f.value]
        undefined = value & ~0x0F
        if undefined:
            names.append(f"0x{undefined:02X}")
        return f"ErrorFlags({'|'.join(names) or 'none'})"

    __str__ = __repr__  # print() and f"{e}" show the names; int(e) is the byte


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
