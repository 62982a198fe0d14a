"""LA replies as values: ``Status``, ``ReadReply``, ``WriteAck``, ``UnknownReply`` (doc 002 3.4)."""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass
from typing import NamedTuple

from motorbus.errors import RemoteProtocolError
from motorbus.protocol.base import LA_REPLY_HEADER, check_int, format_hex
from motorbus.protocol.la.wire import (
    _ERROR_FLAGS,
    CMD_CONTROL,
    CMD_READ,
    CMD_WRITE,
    KNOWN_ERROR_BITS,
    NO_ERRORS,
    STATUS_FRAME_SIZE,
    STATUS_LEN_BYTE,
    WRITE_ACK_LEN_BYTE,
    ControlAction,
    ErrorFlags,
    _is_reply_frame,
    build_frame,
)

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
#: Builds a Status from its 12 decoded fields without re-validating them (see
#: ``Status``): the tuple's own constructor, one call (``_make`` is three).
_make_status = functools.partial(tuple.__new__, Status)


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
