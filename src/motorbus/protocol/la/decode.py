"""LA requests decoded back into commands, and the temperature-limit write plan (A2-14)."""

from __future__ import annotations

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import LA_REQUEST_HEADER, Command, check_choice, check_int, format_hex
from motorbus.protocol.la.commands import (
    Broadcast,
    Control,
    Follow,
    LACommand,
    MoveTo,
    ReadRegister,
    ReadTable,
    WriteRegister,
    WriteTable,
)
from motorbus.protocol.la.table import Register
from motorbus.protocol.la.wire import (
    BROADCAST_ENTRY_SIZE,
    BROADCAST_ID,
    CMD_BROADCAST_FOLLOW,
    CMD_BROADCAST_MOVE,
    CMD_CONTROL,
    CMD_FOLLOW,
    CMD_FOLLOW_NO_REPLY,
    CMD_MOVE,
    CMD_MOVE_NO_REPLY,
    CMD_READ,
    CMD_WRITE,
    CONTROL_LEN_BYTE,
    MOTION_LEN_BYTE,
    READ_REQUEST_LEN_BYTE,
    TARGET_INDEX,
    TEMPERATURE_GAP_C10,
    BroadcastMode,
    ControlAction,
    frame_is_valid,
)

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
