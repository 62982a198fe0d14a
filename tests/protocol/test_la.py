"""Tests of the Inspire LA "55 AA" protocol module (doc 002, docs/protocols.md part C)."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import Command, parse_hex
from motorbus.protocol.la import (
    BROADCAST_ID,
    MAX_BROADCAST_ENTRIES,
    STATUS_FRAME_SIZE,
    BaudCode,
    Broadcast,
    BroadcastMode,
    Control,
    ControlAction,
    ErrorFlags,
    Follow,
    MoveTo,
    ReadRegister,
    ReadReply,
    ReadTable,
    Register,
    Status,
    UnknownReply,
    WriteAck,
    WriteRegister,
    WriteTable,
    build_frame,
    decode_reply,
    decode_request,
    encode_status,
    frame_is_valid,
    la_checksum,
    split_broadcast,
    temperature_limit_writes,
)
from tests.vectors import vectors_of


def _la_vectors() -> list[dict[str, Any]]:
    return vectors_of("inspire_la_55aa")


LA_VECTORS = _la_vectors()
REQUEST_VECTORS = [v for v in LA_VECTORS if v["decoded"]["header"] == "55 AA"]
REPLY_VECTORS = [v for v in LA_VECTORS if "reply_hex" in v]


def _vid(v: dict[str, Any]) -> str:
    return str(v["description"])[:40]


def _command_for(decoded: dict[str, Any]) -> Command:
    """Build, from a vector's "decoded" block, the command our API would use."""
    ident = decoded["id"]
    cmd = int(decoded["cmd"], 16)
    if cmd == 0x01:
        reg = Register.by_index(int(decoded["index_or_param1"], 16))
        assert reg.size == decoded["read_count"]
        return ReadRegister(ident, reg)
    if cmd == 0x02:
        reg = Register.by_index(int(decoded["index_or_param1"], 16))
        return WriteRegister(ident, reg, decoded["value"])
    if cmd in (0x21, 0x03):
        return MoveTo(ident, decoded["value"], reply=cmd == 0x21)
    if cmd in (0x20, 0x19):
        return Follow(ident, decoded["value"], reply=cmd == 0x20)
    if cmd == 0x04:
        return Control(ident, ControlAction(int(decoded["mc_sub"], 16)))
    if cmd in (0xF2, 0xF3):
        entries = tuple((t["id"], t["target_position"]) for t in decoded["targets"])
        return Broadcast(BroadcastMode(cmd), entries)
    raise AssertionError(f"vector with unexpected cmd {cmd:#x}")


# --- vectors ---------------------------------------------------------------------------------


def test_vectors_are_present() -> None:
    assert len(REQUEST_VECTORS) >= 19
    assert len(REPLY_VECTORS) >= 1


@pytest.mark.parametrize("vector", REQUEST_VECTORS, ids=_vid)
def test_encoder_reproduces_document_request(vector: dict[str, Any]) -> None:
    cmd = _command_for(vector["decoded"])
    expected = parse_hex(vector.get("request_hex_corrected", vector["request_hex"]))
    assert cmd.encode() == expected
    assert decode_request(expected) == cmd
    assert frame_is_valid(expected)


@pytest.mark.parametrize("vector", REQUEST_VECTORS, ids=_vid)
def test_document_reply_expectations(vector: dict[str, Any]) -> None:
    cmd = _command_for(vector["decoded"])
    if vector.get("expected_reply_hex"):
        reply = parse_hex(vector["expected_reply_hex"])
        assert cmd.matches_reply(reply)
    elif vector.get("expected_reply") == "none" or vector.get("expected_reply_hex", 1) is None:
        assert cmd.reply_lengths() == ()
    else:
        assert STATUS_FRAME_SIZE in cmd.reply_lengths()


def test_v3_documented_checksum_is_refused() -> None:
    (vector,) = [v for v in LA_VECTORS if not v.get("checksum", {}).get("ok", True)]
    documented = parse_hex(vector["request_hex"])
    assert documented[-1] == 0x28
    assert not frame_is_valid(documented)
    with pytest.raises(RemoteProtocolError) as info:
        decode_request(documented)
    assert info.value.raw == documented
    assert Follow(3, 1000, reply=False).encode() == parse_hex("55 AA 04 03 19 37 E8 03 42")


@pytest.mark.parametrize("vector", REPLY_VECTORS, ids=_vid)
def test_document_read_reply_decodes(vector: dict[str, Any]) -> None:
    raw = parse_hex(vector["reply_hex"])
    request = decode_request(parse_hex(vector["request_hex"]))
    assert isinstance(request, ReadRegister)
    assert request.decode_reply(raw) == vector["decoded"]["value"] == 600
    assert decode_reply(raw) == ReadReply(1, 0x62, bytes((0x58, 0x02)))


STATUS_VECTORS = [v for v in LA_VECTORS if v["decoded"].get("length") == 17]


@pytest.mark.parametrize("vector", STATUS_VECTORS, ids=_vid)
def test_document_status_decodes(vector: dict[str, Any]) -> None:
    d = vector["decoded"]
    raw = parse_hex(vector["expected_reply_hex"])
    status = decode_reply(raw)
    assert isinstance(status, Status)
    assert status.target == d["target_position_u16"] == 1003  # V4: EB 03 is 1003
    assert status.position == d["current_position_s16"]
    assert status.temperature == d["temperature_degC_s8"]
    assert status.current == d["current_u16"]
    assert status.force == d["force_g_s16 (B14 low | B16 high)"]
    assert status.errors == int(d["error_flags"], 16)
    assert status.internal1 == d["internal1_u16"]
    assert status.internal2 == d["internal2_u16"]
    assert status.cmd_echo == int(d["cmd_echo"], 16)
    assert status.param2 == int(d["param2"], 16)
    assert status.fault == bool(d["error_bits"])
    assert status.encode() == raw


def test_document_short_write_ack() -> None:
    (vector,) = [v for v in LA_VECTORS if "reserved_ack_byte" in v["decoded"]]
    raw = parse_hex(vector["expected_reply_hex"])
    request = decode_request(parse_hex(vector["request_hex"]))
    assert request == WriteRegister(1, Register.TARGET, 1300)
    assert request.matches_reply(raw)
    assert request.decode_reply(raw) == WriteAck(1, 0x37, 0)
    assert decode_reply(raw) == WriteAck(1, 0x37, 0)


# --- frames ------------------------------------------------------------------------------------


def test_checksum_and_build_frame() -> None:
    frame = build_frame(b"\x55\xaa", bytes((0x01, 0x01, 0x62, 0x02)))
    assert frame == parse_hex("55 AA 03 01 01 62 02 69")
    assert la_checksum(frame[:-1]) == 0x69


@pytest.mark.parametrize(
    "raw",
    [
        "55 AA 03 01 01 62 02 68",  # checksum
        "55 AA 04 01 01 62 02 6A",  # Len disagrees with size
        "AB 55 03 01 01 62 02 69",  # header
        "55 AA 00 01 01",  # too short
    ],
)
def test_frame_is_valid_refuses(raw: str) -> None:
    assert not frame_is_valid(parse_hex(raw))


def test_status_echoing_request_cmd_is_accepted() -> None:
    move = MoveTo(1, 1000)
    echo = encode_status(1, target=1000, position=10, cmd_echo=0x21, param2=0x00)
    other = encode_status(1, target=1000, position=10, cmd_echo=0x20)
    wrong_id = encode_status(2, target=1000, position=10)
    assert move.matches_reply(echo)
    assert not move.matches_reply(other)
    assert not move.matches_reply(wrong_id)
    assert move.decode_reply(echo).cmd_echo == 0x21
    with pytest.raises(RemoteProtocolError):
        move.decode_reply(wrong_id)


def test_force_is_split_around_error_byte() -> None:
    raw = encode_status(1, target=0, position=0, force=-2, errors=0x05)
    assert raw[14] == 0xFE and raw[15] == 0x05 and raw[16] == 0xFF
    status = decode_reply(raw)
    assert isinstance(status, Status)
    assert status.force == -2
    assert status.errors == ErrorFlags.STALL | ErrorFlags.OVER_CURRENT
    assert status.fault


def test_unknown_error_bits_are_kept_and_not_a_fault() -> None:
    status = Status.decode(encode_status(1, target=0, position=0, errors=0x30))
    assert int(status.errors) == 0x30
    assert not status.fault


def test_negative_current_is_reported_absolute() -> None:
    raw = bytearray(encode_status(1, target=0, position=0))
    raw[12:14] = (-150).to_bytes(2, "little", signed=True)
    raw[-1] = la_checksum(raw[:-1])
    status = decode_reply(bytes(raw))
    assert isinstance(status, Status)
    assert status.current == 150


def test_unknown_reply() -> None:
    raw = build_frame(b"\xaa\x55", bytes((1, 0x30, 0x00, 0x01)))
    assert decode_reply(raw) == UnknownReply(1, 0x30, b"\x00\x01", raw)


# --- commands ------------------------------------------------------------------------------------


def test_id_write_accepts_old_or_new_id() -> None:
    cmd = WriteRegister(3, Register.ID, 2)
    assert cmd.encode() == parse_hex("55 AA 03 03 02 02 02 0C")
    for ident in (3, 2):
        assert cmd.matches_reply(encode_status(ident, target=0, position=0, cmd_echo=0x02))
        ack = build_frame(b"\xaa\x55", bytes((ident, 0x02, 0x02, 0x00)))
        assert cmd.matches_reply(ack)
    assert not cmd.matches_reply(encode_status(4, target=0, position=0))
    assert WriteTable(3, 0, bytes((0xAA, 0x55, 7))).matches_reply(
        encode_status(7, target=0, position=0)
    )


def test_write_target_starts_motion() -> None:
    assert WriteRegister(1, Register.TARGET, 1300).starts_motion
    assert not WriteRegister(1, Register.OVER_CURRENT_LIMIT, 1000).starts_motion
    assert WriteTable(1, 0x36, b"\x00\x01\x02").starts_motion
    assert not WriteTable(1, 0x20, b"\x00\x01").starts_motion
    assert MoveTo(1, 5).starts_motion and Follow(1, 5).starts_motion
    assert not Control(1, ControlAction.WORK).starts_motion


def test_broadcast_id_means_no_reply() -> None:
    for cmd in (
        MoveTo(BROADCAST_ID, 5),
        Follow(BROADCAST_ID, 5),
        Control(BROADCAST_ID, ControlAction.ESTOP),
        WriteTable(BROADCAST_ID, 0x20, b"\xe8\x03"),
        WriteRegister(BROADCAST_ID, Register.OVER_CURRENT_LIMIT, 1000),
        MoveTo(1, 5, reply=False),
        Follow(1, 5, reply=False),
        Broadcast(BroadcastMode.FOLLOW, ((1, 2),)),
    ):
        assert cmd.reply_lengths() == ()
        assert not cmd.expects_reply
        assert not cmd.matches_reply(encode_status(1, target=5, position=5))


def test_reads_refuse_broadcast_id() -> None:
    with pytest.raises(LocalProtocolError, match=r"id=255.*1\.\.254"):
        ReadTable(BROADCAST_ID, 2, 1)
    with pytest.raises(LocalProtocolError, match="id"):
        ReadRegister(BROADCAST_ID, Register.POSITION)


def test_write_register_refuses_read_only() -> None:
    with pytest.raises(LocalProtocolError, match=r"POSITION.*read-only"):
        WriteRegister(1, Register.POSITION, 5)


def test_read_register_decodes_signed() -> None:
    cmd = ReadRegister(1, Register.POSITION)
    reply = build_frame(
        b"\xaa\x55", bytes((1, 0x01, 26)) + (-15).to_bytes(2, "little", signed=True)
    )
    assert cmd.decode_reply(reply) == -15
    assert cmd.reply_lengths() == (9,)
    with pytest.raises(RemoteProtocolError):
        ReadRegister(1, Register.FORCE).decode_reply(reply)


def test_register_lookup() -> None:
    assert Register.by_name("target") is Register.TARGET
    assert Register.by_index(0x62) is Register.OVER_TEMPERATURE_LIMIT
    assert Register.at(2, 1) is Register.ID and Register.at(2, 2) is None
    assert Register.BAUD.value.default == BaudCode.B921600
    assert [c.baud for c in BaudCode] == [19200, 57600, 115200, 921600]
    with pytest.raises(LocalProtocolError, match="bogus"):
        Register.by_name("bogus")
    with pytest.raises(LocalProtocolError, match="index=3"):
        Register.by_index(3)


def test_split_broadcast() -> None:
    targets = {i: i * 10 for i in range(1, 33)}
    frames = split_broadcast(BroadcastMode.POSITION, targets)
    assert [len(f.entries) for f in frames] == [15, 15, 2]
    assert [e for f in frames for e in f.entries] == list(targets.items())
    assert len(frames[0].encode()) == 51  # 5 + 1 + 3 * 15 (docs/protocols.md C.6)
    assert split_broadcast(BroadcastMode.FOLLOW, []) == []
    with pytest.raises(LocalProtocolError, match="id=4"):
        split_broadcast(BroadcastMode.FOLLOW, [(4, 1), (5, 1), (4, 2)])


@pytest.mark.parametrize(
    ("build", "field", "allowed"),
    [
        (lambda: MoveTo(1, 2001), "position", "0..2000"),
        (lambda: Follow(0, 5), "id", "1..254"),
        (
            lambda: Control(1, 0x99),  # type: ignore[arg-type]
            "action",
            "4, 35, 20, 32, 34, 30",
        ),
        (lambda: ReadTable(1, 200, 60), "count", "1..55"),
        (lambda: ReadTable(1, 255, 1), "index", "0..254"),
        (lambda: WriteTable(1, 0, b""), "len(data)", "1..253"),
        (
            lambda: WriteRegister(1, Register.OVER_CURRENT_LIMIT, 200),
            "over_current_limit",
            "300..1500",
        ),
        (lambda: WriteRegister(1, Register.BAUD, 4), "baud", "0..3"),
        (lambda: Broadcast(BroadcastMode.POSITION, ()), "len(entries)", "1..15"),
        (
            lambda: Broadcast(BroadcastMode.POSITION, tuple((i, 0) for i in range(1, 17))),
            "len(entries)",
            "1..15",
        ),
        (lambda: Broadcast(BroadcastMode.POSITION, ((1, 0), (1, 5))), "id=1", "once"),
        (
            lambda: Broadcast(0xF4, ((1, 0),)),  # type: ignore[arg-type]
            "mode",
            "242, 243",
        ),
    ],
)
def test_bad_values_name_field_and_range(build: Any, field: str, allowed: str) -> None:
    with pytest.raises(LocalProtocolError) as info:
        build()
    assert field in str(info.value)
    assert allowed in str(info.value)


def test_bool_is_not_a_position() -> None:
    with pytest.raises(LocalProtocolError, match="position"):
        MoveTo(1, True)


# --- temperature limits (A2-14) ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("new", "current", "order"),
    [
        ((705, 605), (800, 600), ["OVER_TEMPERATURE_LIMIT", "RECOVERY_TEMPERATURE"]),  # lowering
        ((400, 300), (800, 600), ["RECOVERY_TEMPERATURE", "OVER_TEMPERATURE_LIMIT"]),
        ((800, 700), (600, 500), ["OVER_TEMPERATURE_LIMIT", "RECOVERY_TEMPERATURE"]),  # raising
        ((800, 600), (800, 600), []),
        ((800, 500), (800, 600), ["RECOVERY_TEMPERATURE"]),
        # present pair invalid (the 3.5.1 read gives 600 with default recovery 600)
        (
            (620, 570),
            (600, 600),
            ["RECOVERY_TEMPERATURE", "OVER_TEMPERATURE_LIMIT", "RECOVERY_TEMPERATURE"],
        ),
    ],
)
def test_temperature_limit_order(
    new: tuple[int, int], current: tuple[int, int], order: list[str]
) -> None:
    writes = temperature_limit_writes(3, *new, *current)
    assert [w.register.name for w in writes] == order
    over, rec = current
    for w in writes:
        if w.register is Register.OVER_TEMPERATURE_LIMIT:
            over = w.value
        else:
            rec = w.value
        assert over >= rec + 50
    assert (over, rec) == new


def test_temperature_gap_violation_names_both() -> None:
    with pytest.raises(LocalProtocolError) as info:
        temperature_limit_writes(1, 700, 690, 800, 600)
    assert "over_c10=700" in str(info.value) and "recovery_c10=690" in str(info.value)


@given(
    new_over=st.integers(250, 800),
    new_rec=st.integers(200, 750),
    cur_over=st.integers(250, 800),
    cur_rec=st.integers(200, 750),
)
def test_temperature_limit_intermediate_states_valid(
    new_over: int, new_rec: int, cur_over: int, cur_rec: int
) -> None:
    if new_over < new_rec + 50:
        with pytest.raises(LocalProtocolError):
            temperature_limit_writes(1, new_over, new_rec, cur_over, cur_rec)
        return
    over, rec = cur_over, cur_rec
    for w in temperature_limit_writes(1, new_over, new_rec, cur_over, cur_rec):
        if w.register is Register.OVER_TEMPERATURE_LIMIT:
            over = w.value
        else:
            rec = w.value
        assert over >= rec + 50
    assert (over, rec) == (new_over, new_rec)


# --- properties ------------------------------------------------------------------------------

ids = st.integers(1, 254)
ids_or_broadcast = st.one_of(ids, st.just(BROADCAST_ID))
positions = st.integers(0, 2000)


@st.composite
def write_registers(draw: st.DrawFn) -> WriteRegister:
    reg = draw(st.sampled_from([r for r in Register if r.writable]))
    return WriteRegister(draw(ids_or_broadcast), reg, draw(st.integers(reg.minimum, reg.maximum)))


@st.composite
def table_commands(draw: st.DrawFn) -> Command:
    index = draw(st.integers(0, 254))
    count = draw(st.integers(1, min(253, 255 - index)))
    if draw(st.booleans()):
        return ReadTable(draw(ids), index, count)
    return WriteTable(
        draw(ids_or_broadcast), index, draw(st.binary(min_size=count, max_size=count))
    )


@st.composite
def broadcasts(draw: st.DrawFn) -> Broadcast:
    chosen = draw(st.lists(ids, min_size=1, max_size=MAX_BROADCAST_ENTRIES, unique=True))
    entries = tuple((i, draw(positions)) for i in chosen)
    return Broadcast(draw(st.sampled_from(BroadcastMode)), entries)


commands = st.one_of(
    st.builds(MoveTo, ids_or_broadcast, positions, reply=st.booleans()),
    st.builds(Follow, ids_or_broadcast, positions, reply=st.booleans()),
    st.builds(Control, ids_or_broadcast, st.sampled_from(ControlAction)),
    st.builds(ReadRegister, ids, st.sampled_from(Register)),
    write_registers(),
    table_commands(),
    broadcasts(),
)


@given(commands)
def test_encode_decode_request_round_trip(cmd: Command) -> None:
    raw = cmd.encode()
    assert frame_is_valid(raw)
    decoded = decode_request(raw)
    assert decoded.encode() == raw
    if not isinstance(cmd, ReadTable | WriteTable):
        assert decoded == cmd  # typed commands come back exactly


@given(
    st.builds(
        Status,
        id=st.integers(0, 255),
        target=st.integers(0, 0xFFFF),
        position=st.integers(-0x8000, 0x7FFF),
        temperature=st.integers(-128, 127),
        current=st.integers(0, 0x8000),
        force=st.integers(-0x8000, 0x7FFF),
        errors=st.integers(0, 255).map(ErrorFlags),
        cmd_echo=st.sampled_from([0x04, 0x20, 0x21, 0x02]),
        param1=st.integers(0, 255),
        param2=st.integers(0, 255),
        internal1=st.integers(0, 0xFFFF),
        internal2=st.integers(0, 0xFFFF),
    )
)
def test_status_round_trip(status: Status) -> None:
    raw = status.encode()
    assert len(raw) == STATUS_FRAME_SIZE
    decoded = decode_reply(raw)
    if status.cmd_echo == 0x01:  # pragma: no cover - excluded by the strategy
        return
    assert decoded == status


@given(st.binary(max_size=64))
def test_random_bytes_only_raise_remote_errors(raw: bytes) -> None:
    for decoder in (decode_reply, decode_request):
        try:
            decoder(raw)
        except RemoteProtocolError as err:
            assert err.raw == raw


@given(st.binary(min_size=2, max_size=40), st.sampled_from([b"\x55\xaa", b"\xaa\x55"]))
def test_random_valid_frames_only_raise_remote_errors(body: bytes, header: bytes) -> None:
    raw = build_frame(header, body)
    assert frame_is_valid(raw)
    try:
        if header == b"\xaa\x55":
            decode_reply(raw)
        else:
            decode_request(raw)
    except RemoteProtocolError as err:
        assert header == b"\x55\xaa"  # a valid reply frame never raises
        assert err.raw == raw


def test_error_flags_print_as_names() -> None:
    from motorbus.protocol import la

    assert repr(la.ErrorFlags(0)) == "ErrorFlags(none)"
    assert str(la.ErrorFlags.OVER_TEMPERATURE | la.ErrorFlags.STALL) == (
        "ErrorFlags(STALL|OVER_TEMPERATURE)"
    )
    assert f"{la.ErrorFlags(0x14)}" == "ErrorFlags(OVER_CURRENT|0x10)"  # undefined bits in hex
    assert int(la.ErrorFlags(0x14)) == 0x14
