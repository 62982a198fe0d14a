"""LA requests as frozen ``Command`` values (doc 002 section 3.5)."""

from __future__ import annotations

import functools
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from itertools import starmap
from typing import ClassVar

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import (
    LA_REQUEST_HEADER,
    Command,
    Family,
    FaultState,
    ReplyT_co,
    check_choice,
    check_int,
    format_hex,
)
from motorbus.protocol.la.replies import (
    ReadReply,
    Status,
    WriteAck,
    _is_status_frame,
    decode_status,
)
from motorbus.protocol.la.table import Register
from motorbus.protocol.la.wire import (
    BROADCAST_ID,
    CMD_CONTROL,
    CMD_FOLLOW,
    CMD_FOLLOW_NO_REPLY,
    CMD_MOVE,
    CMD_MOVE_NO_REPLY,
    CMD_READ,
    CMD_WRITE,
    CONTROL_RESERVED,
    FRAME_OVERHEAD,
    MAX_BROADCAST_ENTRIES,
    MAX_TABLE_BYTES,
    STATUS_FRAME_SIZE,
    TABLE_INDEX_MAX,
    TABLE_SIZE,
    TARGET_INDEX,
    WRITE_ACK_FRAME_SIZE,
    BroadcastMode,
    ControlAction,
    _check_id,
    _check_position,
    _is_reply_frame,
    build_frame,
)

#: The ``device_key`` of a broadcast (ID 255), which reaches every actuator.
BROADCAST_KEY = f"la:{BROADCAST_ID}"
#: One broadcast entry on the wire: ID, then the position low byte first.
_ENTRY = struct.Struct("<BH")

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

    def reaches(self, key: str) -> bool:
        """True for this actuator's key; a broadcast (``"la:255"``) reaches every
        actuator, and every actuator's command shares its device with a broadcast."""
        own = self.device_key
        if key == own:
            return True
        return key.startswith("la:") and BROADCAST_KEY in (key, own)

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

    def decode_matched(self, raw: bytes) -> Status:
        """``decode_reply`` of a frame ``matches_reply`` accepted: no check twice."""
        return decode_status(bytes(raw), checked=True)


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
        raw = bytes(raw)
        # _matches_status, inline (one ID, one CMD): every status poll passes here.
        return (
            self.id != BROADCAST_ID
            and _is_status_frame(raw)
            and raw[3] == self.id
            and raw[4] == CMD_CONTROL
        )

    def decode_reply(self, raw: bytes) -> Status:
        """Decode the status reply.

        Raises:
            RemoteProtocolError: ``raw`` is not a reply to this request.
        """
        return self._decode_checked_status(bytes(raw))

    def decode_matched(self, raw: bytes) -> Status:
        """``decode_reply`` of a frame ``matches_reply`` accepted: no check twice."""
        return decode_status(bytes(raw), checked=True)


@functools.cache
def control_frame(ident: int, action: ControlAction) -> Control:
    """``Control(ident, action)``, made (and checked) once per pair: a command is an
    immutable value, and status queries go out every tick (polls, ``status()``)."""
    return Control(ident, action)


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
    #: The encoded frame, kept by the first ``encode()`` (a stream encodes its tick's
    #: frame ahead of the deadline, so that only the write is left at the deadline).
    _raw: bytes | None = field(default=None, init=False, repr=False, compare=False)

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
        object.__setattr__(obj, "_raw", None)
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
        if self._raw is not None:
            return self._raw
        # Streams encode one of these per tick and bus: each entry packed in C (a
        # generator here was one call per byte, 46 of a 15-actuator tick's calls).
        body = bytes((BROADCAST_ID, self.mode)) + b"".join(starmap(_ENTRY.pack, self.entries))
        raw = build_frame(LA_REQUEST_HEADER, body)
        object.__setattr__(self, "_raw", raw)
        return raw

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
