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

The package: ``wire`` (frame layout, IDs, command codes, frame helpers, enums),
``table`` (the control table, ``Register``), ``replies`` (``Status`` and the other
replies), ``commands`` and ``decode`` (requests back into commands, temperature-limit
plans); the public names (``__all__``) are importable from here, the rest from their
modules.
"""

from __future__ import annotations

from motorbus.protocol.la.commands import (
    Broadcast as Broadcast,
)
from motorbus.protocol.la.commands import (
    Control as Control,
)
from motorbus.protocol.la.commands import (
    Follow as Follow,
)
from motorbus.protocol.la.commands import (
    LACommand as LACommand,
)
from motorbus.protocol.la.commands import (
    MoveTo as MoveTo,
)
from motorbus.protocol.la.commands import (
    ReadRegister as ReadRegister,
)
from motorbus.protocol.la.commands import (
    ReadTable as ReadTable,
)
from motorbus.protocol.la.commands import (
    WriteRegister as WriteRegister,
)
from motorbus.protocol.la.commands import (
    WriteTable as WriteTable,
)
from motorbus.protocol.la.commands import (
    control_frame as control_frame,
)
from motorbus.protocol.la.commands import (
    split_broadcast as split_broadcast,
)
from motorbus.protocol.la.decode import (
    decode_request as decode_request,
)
from motorbus.protocol.la.decode import (
    temperature_limit_writes as temperature_limit_writes,
)
from motorbus.protocol.la.replies import (
    ReadReply as ReadReply,
)
from motorbus.protocol.la.replies import (
    Status as Status,
)
from motorbus.protocol.la.replies import (
    UnknownReply as UnknownReply,
)
from motorbus.protocol.la.replies import (
    WriteAck as WriteAck,
)
from motorbus.protocol.la.replies import (
    decode_reply as decode_reply,
)
from motorbus.protocol.la.replies import (
    decode_status as decode_status,
)
from motorbus.protocol.la.replies import (
    encode_status as encode_status,
)
from motorbus.protocol.la.table import (
    Register as Register,
)
from motorbus.protocol.la.table import (
    RegisterInfo as RegisterInfo,
)
from motorbus.protocol.la.wire import (
    BROADCAST_ENTRY_SIZE as BROADCAST_ENTRY_SIZE,
)
from motorbus.protocol.la.wire import (
    BROADCAST_ID as BROADCAST_ID,
)
from motorbus.protocol.la.wire import (
    CMD_BROADCAST_FOLLOW as CMD_BROADCAST_FOLLOW,
)
from motorbus.protocol.la.wire import (
    CMD_BROADCAST_MOVE as CMD_BROADCAST_MOVE,
)
from motorbus.protocol.la.wire import (
    CMD_CONTROL as CMD_CONTROL,
)
from motorbus.protocol.la.wire import (
    CMD_FOLLOW as CMD_FOLLOW,
)
from motorbus.protocol.la.wire import (
    CMD_FOLLOW_NO_REPLY as CMD_FOLLOW_NO_REPLY,
)
from motorbus.protocol.la.wire import (
    CMD_MOVE as CMD_MOVE,
)
from motorbus.protocol.la.wire import (
    CMD_MOVE_NO_REPLY as CMD_MOVE_NO_REPLY,
)
from motorbus.protocol.la.wire import (
    CMD_READ as CMD_READ,
)
from motorbus.protocol.la.wire import (
    CMD_WRITE as CMD_WRITE,
)
from motorbus.protocol.la.wire import (
    ID_MAX as ID_MAX,
)
from motorbus.protocol.la.wire import (
    ID_MIN as ID_MIN,
)
from motorbus.protocol.la.wire import (
    KNOWN_ERROR_BITS as KNOWN_ERROR_BITS,
)
from motorbus.protocol.la.wire import (
    MAX_BROADCAST_ENTRIES as MAX_BROADCAST_ENTRIES,
)
from motorbus.protocol.la.wire import (
    MAX_FRAME_SIZE as MAX_FRAME_SIZE,
)
from motorbus.protocol.la.wire import (
    POSITION_MAX as POSITION_MAX,
)
from motorbus.protocol.la.wire import (
    POSITION_MIN as POSITION_MIN,
)
from motorbus.protocol.la.wire import (
    REPORTED_POSITION_MAX as REPORTED_POSITION_MAX,
)
from motorbus.protocol.la.wire import (
    REPORTED_POSITION_MIN as REPORTED_POSITION_MIN,
)
from motorbus.protocol.la.wire import (
    STATUS_FRAME_SIZE as STATUS_FRAME_SIZE,
)
from motorbus.protocol.la.wire import (
    STATUS_LEN_BYTE as STATUS_LEN_BYTE,
)
from motorbus.protocol.la.wire import (
    TARGET_INDEX as TARGET_INDEX,
)
from motorbus.protocol.la.wire import (
    TEMPERATURE_GAP_C10 as TEMPERATURE_GAP_C10,
)
from motorbus.protocol.la.wire import (
    WRITE_ACK_FRAME_SIZE as WRITE_ACK_FRAME_SIZE,
)
from motorbus.protocol.la.wire import (
    BaudCode as BaudCode,
)
from motorbus.protocol.la.wire import (
    BroadcastMode as BroadcastMode,
)
from motorbus.protocol.la.wire import (
    ControlAction as ControlAction,
)
from motorbus.protocol.la.wire import (
    ErrorFlags as ErrorFlags,
)
from motorbus.protocol.la.wire import (
    build_frame as build_frame,
)
from motorbus.protocol.la.wire import (
    frame_is_valid as frame_is_valid,
)
from motorbus.protocol.la.wire import (
    la_checksum as la_checksum,
)

__all__ = [
    "BROADCAST_ENTRY_SIZE",
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
    "KNOWN_ERROR_BITS",
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
    "LACommand",
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
    "control_frame",
    "decode_reply",
    "decode_request",
    "decode_status",
    "encode_status",
    "frame_is_valid",
    "la_checksum",
    "split_broadcast",
    "temperature_limit_writes",
]
