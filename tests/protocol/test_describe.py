"""describe(): frames, events and garbage as JSON-ready descriptions and one-line text."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.protocol import la
from motorbus.protocol.base import Direction, Family, format_hex, parse_hex, sum8
from motorbus.protocol.describe import (
    KIND_EVENT,
    KIND_FRAME,
    KIND_GARBAGE,
    NAME_UNKNOWN,
    Description,
    describe,
)
from motorbus.protocol.reassembler import Discarded, Frame, ProjectFinishedMarker, Reassembler
from tests.vectors import load_vectors

LA, PROJECT, QUAD = Family.LA, Family.PROJECT_STEPPER, Family.QUAD_STEPPER
REQ, REP = Direction.REQUEST, Direction.REPLY
STATUS_HEX = "AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 05 01 08 07 0A 07 99"
FAMILY_OF_KIND = {
    "inspire_la_55aa": LA,
    "ffaa11_project_stepper": PROJECT,
    "ffaa9_4axis_stepper": QUAD,
}


def frame(family: Family, direction: Direction, text: str) -> Frame:
    return Frame(family, direction, parse_hex(text))


def la_frame(header: str, body: bytes) -> bytes:
    """An LA frame around ``body`` (ID CMD IDX data...), Len and checksum computed."""
    length = len(body) - 1
    return parse_hex(header) + bytes([length]) + body + bytes([sum8(bytes([length]) + body)])


# -- table: frames of each family -------------------------------------------------------------

CASES: list[tuple[Frame, str, dict[str, Any]]] = [
    (
        frame(LA, REQ, "55 AA 04 01 21 37 14 05 76"),
        "MoveTo",
        {"id": 1, "position": 1300, "reply": True},
    ),
    (
        frame(LA, REQ, "55 AA 04 03 19 37 E8 03 42"),
        "Follow",
        {"id": 3, "position": 1000, "reply": False},
    ),
    (frame(LA, REQ, "55 AA 03 01 04 00 23 2B"), "Control", {"id": 1, "action": "ESTOP"}),
    (
        frame(LA, REQ, "55 AA 04 01 02 37 14 05 57"),
        "WriteRegister",
        {"id": 1, "register": "TARGET", "value": 1300},
    ),
    (
        frame(LA, REQ, "55 AA 03 01 01 62 02 69"),
        "ReadRegister",
        {"id": 1, "register": "OVER_TEMPERATURE_LIMIT"},
    ),
    (
        frame(LA, REQ, "55 AA 07 FF F2 01 E8 03 02 D0 07 BD"),
        "Broadcast",
        {"mode": "POSITION", "entries": [{"id": 1, "position": 1000}, {"id": 2, "position": 2000}]},
    ),
    (
        frame(LA, REP, STATUS_HEX),
        "Status",
        {
            "id": 1,
            "target": 1003,  # EB 03, although the manual's prose says 1000 (V4)
            "position": 990,
            "temperature": 20,
            "current": 100,
            "force": 500,
            "errors": ["STALL", "OVER_CURRENT"],
            "cmd_echo": 4,
            "param1": 0,
            "param2": 0x22,
            "internal1": 1800,
            "internal2": 1802,
            "fault": True,
        },
    ),
    (
        frame(LA, REP, "AA 55 04 01 01 62 58 02 C2"),
        "ReadReply",
        {
            "id": 1,
            "index": 0x62,
            "data": "58 02",
            "register": "OVER_TEMPERATURE_LIMIT",
            "value": 600,
        },
    ),
    (
        frame(LA, REP, "AA 55 03 01 02 37 00 3D"),
        "WriteAck",
        {"id": 1, "index": 0x37, "reserved": 0},
    ),
    (
        frame(PROJECT, REQ, "FF AA 6E 01 01 00 00 00 00 00 19"),
        "SelectProject",
        {"project": 1, "total_steps": 1},
    ),
    (
        frame(PROJECT, REQ, "FF AA 03 04 01 32 00 00 00 01 E4"),
        "DirectionAndStartFrequency",
        {"step": 1, "direction": "REVERSE", "start_hz": 50, "motor": 3},
    ),
    (
        frame(PROJECT, REP, "FF AA 03 04 00 01"),
        "Ack",
        {
            "kind": "STEP",
            "opcode": 4,
            "project": None,
            "motor": 3,
            "step": 1,
            "port": None,
            "value": None,
        },
    ),
    (
        frame(PROJECT, REQ, "FF AA 8E 00 00 00 00 00 00 00 37"),
        "RepeatCount",
        {"count": 0, "forever": False},
    ),
    (
        frame(QUAD, REQ, "FF AA 01 03 40 06 00 00 F3"),
        "RunPulses",
        {"motor": 1, "pulses": 1600},
    ),
    (
        frame(QUAD, REP, "FF AA 00 09 01 00"),
        "Done",
        {"address": 0, "command": 9, "led": None, "motor": None},
    ),
    (
        frame(QUAD, REP, "FF AA BC 00 00 00"),
        "Ack",
        {"address": 0xBC, "command": 0, "led": None, "motor": None},
    ),
]


@pytest.mark.parametrize(("item", "name", "fields"), CASES, ids=[c[1] for c in CASES])
def test_frames_decode_to_their_named_fields(
    item: Frame, name: str, fields: dict[str, Any]
) -> None:
    d = describe(item)
    assert (d.kind, d.family, d.direction, d.name) == (
        KIND_FRAME,
        item.family.value,
        item.direction.value,
        name,
    )
    assert d.fields == fields
    assert d.hex == format_hex(item.raw)
    assert d.reason is None


def test_to_line_matches_the_documented_example() -> None:
    d = describe(frame(LA, REQ, "55 AA 04 01 21 37 14 05 76"))
    assert (
        d.to_line()
        == "la request MoveTo id=1 position=1300 reply=True  [55 AA 04 01 21 37 14 05 76]"
    )


def test_to_line_quotes_values_with_spaces_and_drops_none() -> None:
    line = describe(frame(LA, REP, "AA 55 04 01 01 62 58 02 C2")).to_line()
    assert line == (
        'la reply ReadReply id=1 index=98 data="58 02" register=OVER_TEMPERATURE_LIMIT '
        "value=600  [AA 55 04 01 01 62 58 02 C2]"
    )
    ack = describe(frame(PROJECT, REP, "FF AA 03 04 00 01")).to_line()
    assert ack == "project_stepper reply Ack kind=STEP opcode=4 motor=3 step=1  [FF AA 03 04 00 01]"


def test_to_json_is_serialisable_and_complete() -> None:
    d = describe(frame(LA, REP, STATUS_HEX))
    data = json.loads(json.dumps(d.to_json()))
    assert data == {
        "kind": "frame",
        "family": "la",
        "direction": "reply",
        "name": "Status",
        "fields": d.fields,
        "hex": STATUS_HEX,
    }


def test_undefined_error_bits_are_named_by_position() -> None:
    raw = la.encode_status(1, target=5, position=5, errors=0x31)
    assert describe(Frame(LA, REP, raw)).fields["errors"] == ["STALL", "BIT4", "BIT5"]


def test_project_dump_lists_its_steps() -> None:
    (vector,) = [
        v for v in load_vectors() if v["synthesized"] and v["request_hex"].startswith("FF AA 3E")
    ]
    d = describe(frame(PROJECT, REP, vector["expected_reply_hex"]))
    assert d.name == "ProjectDump"
    assert d.fields["project"] == 1
    assert d.fields["number_of_steps"] == 1
    assert d.fields["subdivision"] == 8
    assert d.fields["step_angle_x100"] == 180
    assert d.fields["steps"] == [
        {
            "run_distance": 1,
            "direction": "REVERSE",
            "start_hz": 50,
            "accel_hz": 30,
            "speed_rpm": 100,
            "output": "NONE",
            "delay_ms": 1000,
            "start_input": "NONE",
            "stop_input": "NONE",
        }
    ]
    # Bulk bytes hidden from the dataclass's repr stay in the hex only.
    assert "reserved" not in d.fields and "unused_steps" not in d.fields
    assert len(d.hex.split()) == 226


# -- events and garbage ------------------------------------------------------------------------


def test_project_finished_is_an_event() -> None:
    d = describe(ProjectFinishedMarker())
    assert (d.kind, d.family, d.direction, d.name, d.fields, d.hex) == (
        KIND_EVENT,
        "project_stepper",
        "reply",
        "ProjectFinished",
        {},
        "EE DD",
    )
    assert d.to_line() == "project_stepper event ProjectFinished  [EE DD]"


def test_garbage_keeps_its_bytes_and_reason() -> None:
    d = describe(Discarded(b"\x55\xaa\x04", "bad checksum"))
    assert (d.kind, d.family, d.direction, d.name, d.hex, d.reason) == (
        KIND_GARBAGE,
        None,
        None,
        "garbage",
        "55 AA 04",
        "bad checksum",
    )
    assert d.to_line() == "garbage (bad checksum) 3 bytes  [55 AA 04]"
    assert d.to_json()["reason"] == "bad checksum"


# -- frames no decoder accepts -----------------------------------------------------------------


def test_unknown_la_request_keeps_its_raw_fields() -> None:
    raw = la_frame("55 AA", bytes([7, 0x55, 0x10, 0xAB, 0xCD]))
    d = describe(Frame(LA, REQ, raw))
    assert d.name == NAME_UNKNOWN
    assert d.fields == {"length": 4, "id": 7, "cmd": 0x55, "index": 0x10, "data": "AB CD"}
    assert d.reason is not None and "0x55" in d.reason


def test_unknown_la_reply_shape_is_named_unknown() -> None:
    raw = la_frame("AA 55", bytes([2, 0x33, 0x01, 0x02]))
    d = describe(Frame(LA, REP, raw))
    assert (d.name, d.fields, d.reason) == (
        NAME_UNKNOWN,
        {"id": 2, "cmd": 0x33, "payload": "01 02"},
        None,
    )


def test_unknown_quad_reply_with_a_family_hint() -> None:
    d = describe(frame(PROJECT, REP, "FF AA 07 77 07 07"), family_hint=QUAD)
    assert (d.family, d.name) == ("quad_stepper", NAME_UNKNOWN)
    assert d.fields == {"address": 7, "command": 0x77, "data": "07 07"}
    assert d.reason is not None


def test_unknown_stepper_request() -> None:
    raw = parse_hex("FF AA 05 77 00 00 00 00")
    raw += bytes([sum8(raw)])
    d = describe(Frame(QUAD, REQ, raw))
    assert d.name == NAME_UNKNOWN
    assert d.fields == {"address": 5, "command": 0x77, "data": "00 00 00 00"}


def test_family_hint_tells_look_alike_stepper_replies_apart() -> None:
    item = frame(PROJECT, REP, "FF AA 00 0C 01 01")
    assert describe(item).fields["kind"] == "OUTPUT"
    quad = describe(item, family_hint=QUAD)
    assert (quad.family, quad.name, quad.fields["led"]) == ("quad_stepper", "Done", 1)
    # LA frames say what they are: the hint does not apply.
    la_item = frame(LA, REQ, "55 AA 04 01 21 37 14 05 76")
    assert describe(la_item, family_hint=QUAD).family == "la"


def test_a_reply_the_guessed_family_refuses_falls_back_to_the_other() -> None:
    # No quad reply has a nonzero r5 after a motor command; the project stepper's step
    # ack does.  Without a hint the other stepper family gets its turn; with one, not.
    item = frame(QUAD, REP, "FF AA 03 04 00 01")
    d = describe(item)
    assert (d.family, d.name, d.fields["step"]) == ("project_stepper", "Ack", 1)
    hinted = describe(item, family_hint=QUAD)
    assert (hinted.family, hinted.name) == ("quad_stepper", NAME_UNKNOWN)


# -- every vector ------------------------------------------------------------------------------


def test_every_vector_frame_is_described_without_unknowns() -> None:
    for v in load_vectors():
        family = FAMILY_OF_KIND[v["device_kind"]]
        request = v.get("request_hex_corrected") or v["request_hex"]
        replies = [v.get(k) for k in ("expected_reply_hex", "reply_hex", "completion_reply_hex")]
        for text, direction in [(request, REQ)] + [(r, REP) for r in replies if r]:
            d = describe(frame(family, direction, text), family_hint=family)
            assert d.name != NAME_UNKNOWN, (v["description"], text, d.reason)
            assert (d.family, d.direction) == (family.value, direction.value)


# -- properties --------------------------------------------------------------------------------


def _check(d: Description) -> None:
    text = json.dumps(d.to_json())
    assert json.loads(text)["hex"] == d.hex
    line = d.to_line()
    assert "\n" not in line and line.endswith(f"[{d.hex}]")


@settings(max_examples=300)
@given(st.binary(max_size=300))
def test_any_stream_is_described_without_raising(data: bytes) -> None:
    r = Reassembler(direction=None)
    items = r.feed(data) + r.end_of_stream()
    seen = b""
    for item in items:
        d = describe(item)
        _check(d)
        seen += bytes.fromhex(d.hex)
    assert seen == data


@settings(max_examples=300)
@given(
    st.sampled_from(list(Family)),
    st.sampled_from(list(Direction)),
    st.binary(max_size=12),
    st.sampled_from([None, *Family]),
)
def test_any_frame_bytes_are_described_without_raising(
    family: Family, direction: Direction, body: bytes, hint: Family | None
) -> None:
    # Valid framing around random contents: the decoders see every odd field value.
    if family is LA:
        raw = la_frame("55 AA" if direction is REQ else "AA 55", bytes([1, 2]) + body)
    elif direction is REQ:
        size = 11 if family is PROJECT else 9
        head = (b"\xff\xaa" + body + bytes(size))[: size - 1]
        raw = head + bytes([sum8(head)])
    else:
        raw = (b"\xff\xaa" + body + bytes(4))[:6]
    d = describe(Frame(family, direction, raw), family_hint=hint)
    _check(d)
    assert d.kind == KIND_FRAME and d.hex == format_hex(raw)
