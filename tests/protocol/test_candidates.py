"""Where a frame may start (``protocol/candidates.py``): the prefilter skips only what the
judge refuses, and no frame of the manuals.

The candidate finder passes over headers whose command bytes no frame carries, in C
(a byte-flag table and big-integer shifts) or in Python (``passes``); the judge applies
the same rules.  These tests hold the three together, and hold them to the manuals: every
frame the library's encoders build (requests, status frames, read replies, acks, stepper
replies and dumps) is still cut whole, in every set-up that may carry it.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.protocol import la, quad_stepper
from motorbus.protocol.base import (
    FF_AA,
    LA_REPLY_HEADER,
    LA_REQUEST_HEADER,
    PROJECT_FINISHED_BYTES,
    Command,
    Direction,
    Family,
    FrameShape,
)
from motorbus.protocol.candidates import (
    FF_ANY,
    FF_REPLY,
    FF_REQUEST,
    FF_REQUEST_ONLY,
    CandidateFinder,
)
from motorbus.protocol.frame_judge import COMPLETE, INVALID, FrameJudge
from motorbus.protocol.frames import (
    LA_ANY_LENGTH_COMMANDS,
    LA_COMMANDS,
    LA_SHORT_MAX_LEN,
    PROJECT_B9_MAX,
    QUAD_ADDRESSES,
    STEPPER_B3_MAX,
    STEPPER_FREE_B3_OPCODE,
)
from motorbus.protocol.la.wire import MAX_TABLE_BYTES
from motorbus.protocol.project_stepper.wire import MAX_STEPS, MOTOR_COMMANDS, OP_REPEAT
from motorbus.protocol.reassembler import Frame, Reassembler
from tests.protocol.test_la import commands as la_commands
from tests.protocol.test_project_stepper import commands as project_commands
from tests.protocol.test_quad_stepper import commands as quad_commands

ALL = tuple(Family)
#: (direction, families) of the reassemblers the library builds.
SETUPS = [
    (Direction.REPLY, (Family.LA,)),
    (Direction.REPLY, (Family.PROJECT_STEPPER,)),
    (Direction.REPLY, (Family.QUAD_STEPPER,)),
    (Direction.REPLY, ALL),
    (Direction.REQUEST, (Family.LA,)),
    (Direction.REQUEST, (Family.PROJECT_STEPPER,)),
    (Direction.REQUEST, (Family.QUAD_STEPPER,)),
    (Direction.REQUEST, ALL),
    (None, (Family.LA,)),
    (None, ALL),
]
ANY_REPLY = (FrameShape.exact(6, 0xFF, 0xAA),)


def cut(raw: bytes, direction: Direction | None, families: tuple[Family, ...]) -> list[object]:
    r = Reassembler(direction=direction, families=families)
    return [*r.feed(raw), *r.end_of_stream()]


# -- the facts the rules stand on ---------------------------------------------------------


def test_the_command_bytes_are_the_manuals() -> None:
    assert {
        la.CMD_READ,
        la.CMD_WRITE,
        la.CMD_MOVE_NO_REPLY,
        la.CMD_CONTROL,
        la.CMD_FOLLOW_NO_REPLY,
        la.CMD_FOLLOW,
        la.CMD_MOVE,
        la.CMD_BROADCAST_MOVE,
        la.CMD_BROADCAST_FOLLOW,
    } == LA_COMMANDS
    assert {la.CMD_READ, la.CMD_WRITE} == LA_ANY_LENGTH_COMMANDS
    # The longest frame of any other command: a broadcast of 15 entries.
    assert LA_SHORT_MAX_LEN == 1 + la.BROADCAST_ENTRY_SIZE * la.MAX_BROADCAST_ENTRIES
    assert la.STATUS_LEN_BYTE <= LA_SHORT_MAX_LEN
    assert STEPPER_FREE_B3_OPCODE == OP_REPEAT
    assert max(MOTOR_COMMANDS) == STEPPER_B3_MAX
    assert PROJECT_B9_MAX == MAX_STEPS
    assert {
        *quad_stepper.MOTORS,
        quad_stepper.ADDRESS_ALL,
        quad_stepper.ADDRESS_IO,
        quad_stepper.ADDRESS_SAVE,
    } == QUAD_ADDRESSES


# -- every frame of the manuals is cut whole -----------------------------------------------


@given(la_commands)
def test_every_la_request_is_a_frame(cmd: Command[object]) -> None:
    raw = cmd.encode()
    for direction, families in ((Direction.REQUEST, (Family.LA,)), (Direction.REQUEST, ALL)):
        assert cut(raw, direction, families) == [Frame(Family.LA, Direction.REQUEST, raw)]
    assert cut(raw, None, ALL) == [Frame(Family.LA, Direction.REQUEST, raw)]


la_replies = st.one_of(
    # A status, its B4 the status CMD or an echo of any request's (A2-04).
    st.builds(
        lambda ident, cmd, data: la.build_frame(LA_REPLY_HEADER, bytes((ident, cmd)) + data),
        st.integers(1, 254),
        st.sampled_from(sorted(LA_COMMANDS)),
        st.binary(min_size=16, max_size=16),
    ),
    # A read reply: ID 01 IDX and 1..253 table bytes.
    st.builds(
        lambda ident, index, data: la.build_frame(
            LA_REPLY_HEADER, bytes((ident, la.CMD_READ, index)) + data
        ),
        st.integers(1, 254),
        st.integers(0, 254),
        st.binary(min_size=1, max_size=MAX_TABLE_BYTES),
    ),
    # The short write ack.
    st.builds(
        lambda ident, index: la.build_frame(
            LA_REPLY_HEADER, bytes((ident, la.CMD_WRITE, index, 0))
        ),
        st.integers(1, 254),
        st.integers(0, 254),
    ),
)


@given(la_replies)
def test_every_la_reply_is_a_frame(raw: bytes) -> None:
    for direction, families in ((Direction.REPLY, (Family.LA,)), (Direction.REPLY, ALL)):
        assert cut(raw, direction, families) == [Frame(Family.LA, Direction.REPLY, raw)]
    assert cut(raw, None, ALL) == [Frame(Family.LA, Direction.REPLY, raw)]


@given(st.one_of(project_commands, quad_commands))
def test_every_stepper_request_is_a_frame(cmd: Command[object]) -> None:
    raw = cmd.encode()
    frame = Frame(cmd.family, Direction.REQUEST, raw)
    for direction, families in ((Direction.REQUEST, (cmd.family,)), (Direction.REQUEST, ALL)):
        assert cut(raw, direction, families) == [frame]
    assert cut(raw, None, (cmd.family,)) == [frame]


@st.composite
def stepper_replies(draw: st.DrawFn) -> tuple[Command[object], bytes]:
    """A command and one of its replies (or done replies), every free byte drawn."""
    cmd = draw(st.one_of(project_commands, quad_commands))
    shape = draw(st.sampled_from((*cmd.reply_shapes(), *cmd.done_shapes())))
    head = bytes(
        draw(st.sampled_from(sorted(allowed)) if allowed is not None else st.integers(0, 255))
        for allowed in shape.pattern
    )
    rest = shape.length - len(head)
    return cmd, head + draw(st.binary(min_size=rest, max_size=rest))


@settings(max_examples=300)
@given(stepper_replies())
def test_every_stepper_reply_is_a_frame_with_or_without_an_expectation(
    case: tuple[Command[object], bytes],
) -> None:
    cmd, raw = case
    frame = Frame(cmd.family, Direction.REPLY, raw)
    for expected in (None, (*cmd.reply_shapes(), *cmd.done_shapes())):
        r = Reassembler(direction=Direction.REPLY, families=(cmd.family,))
        r.expect(expected)
        assert [*r.feed(raw), *r.end_of_stream()] == [frame], expected


# -- the prefilter, the judge and the C marks agree ----------------------------------------

#: Bytes the rules look at, and any byte.
SPECIAL = [
    *(0xAA, 0x55, 0xFF, 0xEE, 0xDD, 0x8E, 0x00, 0x03, 0x0A, 0x0B, 0x0F, 0x10, 0x2E, 0x2F),
    *LA_COMMANDS,
    *QUAD_ADDRESSES,
]
junk = st.lists(
    st.one_of(
        st.sampled_from(SPECIAL),
        st.integers(0, 255),
    ),
    max_size=120,
).map(bytes)
#: Header bytes with the bytes the rules look at: LA Len and CMD, stepper bytes 2 and 3.
rule_bytes = st.one_of(st.sampled_from(SPECIAL), st.integers(0, 255))
headed = st.one_of(
    st.builds(
        lambda header, length, ident, cmd: header + bytes((length, ident, cmd)),
        st.sampled_from([LA_REPLY_HEADER, LA_REQUEST_HEADER]),
        rule_bytes,
        rule_bytes,
        rule_bytes,
    ),
    st.builds(lambda b2, b3: FF_AA + bytes((b2, b3)), rule_bytes, rule_bytes),
    # Up to byte 9 (a project request's step) with the bytes between as they come.
    st.builds(
        lambda b2, b3, middle, b9: FF_AA + bytes((b2, b3)) + middle + bytes((b9,)),
        rule_bytes,
        rule_bytes,
        st.binary(min_size=5, max_size=5),
        rule_bytes,
    ),
)
pieces = st.one_of(
    junk,
    headed,
    st.sampled_from([LA_REPLY_HEADER, LA_REQUEST_HEADER, FF_AA, PROJECT_FINISHED_BYTES]),
    st.builds(
        la.build_frame,
        st.sampled_from([LA_REPLY_HEADER, LA_REQUEST_HEADER]),
        st.binary(min_size=2, max_size=60),
    ),
    la_commands.map(lambda c: c.encode()),
    st.one_of(project_commands, quad_commands).map(lambda c: c.encode()),
)
streams = st.lists(pieces, max_size=8).map(b"".join)
expectations = st.sampled_from([None, ANY_REPLY, ()])


def judge_for(
    setup: tuple[Direction | None, tuple[Family, ...]], expected: tuple[FrameShape, ...] | None
) -> FrameJudge:
    judge = FrameJudge(*setup)
    judge.expected = expected
    return judge


def header_positions(buf: bytes, headers: tuple[bytes, ...]) -> list[int]:
    return [p for p in range(len(buf) - 1) if buf[p : p + 2] in headers]


@settings(max_examples=300)
@given(buf=streams, setup=st.sampled_from(SETUPS), expected=expectations)
def test_the_prefilter_never_skips_a_header_the_judge_accepts(
    buf: bytes,
    setup: tuple[Direction | None, tuple[Family, ...]],
    expected: tuple[FrameShape, ...] | None,
) -> None:
    judge = judge_for(setup, expected)
    finder = judge.finder
    marks = finder.marks(buf)
    for p in header_positions(buf, judge.headers):
        for final in (False, True):
            if judge.parse_at(buf, p, final)[0] == COMPLETE:
                assert finder.passes(buf, p), (buf.hex(" "), p)
                assert marks[p] == 1 or buf[p : p + 2] == PROJECT_FINISHED_BYTES


@settings(max_examples=300)
@given(buf=streams, ext=junk, setup=st.sampled_from(SETUPS), expected=expectations)
def test_a_skipped_header_is_refused_whatever_follows(
    buf: bytes,
    ext: bytes,
    setup: tuple[Direction | None, tuple[Family, ...]],
    expected: tuple[FrameShape, ...] | None,
) -> None:
    judge = judge_for(setup, expected)
    for p in header_positions(buf, judge.headers):
        if not judge.finder.passes(buf, p):
            assert judge.parse_at(buf + ext, p, True)[0] == INVALID, (buf.hex(" "), p)


@settings(max_examples=300)
@given(
    buf=streams,
    headers=st.sampled_from(
        [
            (LA_REPLY_HEADER,),
            (LA_REQUEST_HEADER, FF_AA),
            (LA_REPLY_HEADER, LA_REQUEST_HEADER, FF_AA),
        ]
    ),
    rule=st.sampled_from([FF_ANY, FF_REPLY, FF_REQUEST, FF_REQUEST_ONLY]),
    steppers=st.sampled_from([(True, True), (True, False), (False, True)]),
)
def test_the_c_marks_are_the_python_check(
    buf: bytes, headers: tuple[bytes, ...], rule: int, steppers: tuple[bool, bool]
) -> None:
    quad, project = steppers
    finder = CandidateFinder(headers, rule, quad=quad, project=project)
    expected = bytes(buf[p : p + 2] in headers and finder.passes(buf, p) for p in range(len(buf)))
    assert finder.marks_in_c(buf) == expected, buf.hex(" ")
    table = finder._anchor_table()
    if table is None:
        assert rule == FF_ANY and FF_AA in headers  # no anchor: marked in C throughout
    else:
        # The anchors, however dense: the marks are the same whichever way they come.
        assert finder.marks_from_anchors(buf, buf.translate(table)) == expected, buf.hex(" ")
    assert finder.marks(buf) == expected


@pytest.mark.parametrize("rule", [FF_REPLY, FF_REQUEST, FF_REQUEST_ONLY])
@pytest.mark.parametrize("steppers", [(True, True), (True, False), (False, True)])
def test_marks_agree_on_headers_whose_rule_bytes_are_at_the_end(
    rule: int, steppers: tuple[bool, bool]
) -> None:
    # Each cut leaves a header near the end: its rule bytes there or still due.
    headers = (LA_REPLY_HEADER, LA_REQUEST_HEADER, FF_AA)
    finder = CandidateFinder(headers, rule, quad=steppers[0], project=steppers[1])
    table = finder._anchor_table()
    assert table is not None
    for frame in (
        "ffaa001000",
        "ffaa000500",
        "ffaa8e2000",
        "ffaa050500000000000b",  # byte 2 no quad address, byte 9 no step
        "ffaa030500000000000b",  # byte 2 a quad address
        "ffaa050500000000000a",  # byte 9 a step
        "aa55300303",
        "aa55300101",
        "55aa2f0021",
    ):
        whole = bytes.fromhex(frame)
        for cut in range(2, len(whole) + 1):
            buf = b"\x10\x33" + whole[:cut]
            expected = bytes(
                buf[p : p + 2] in headers and finder.passes(buf, p) for p in range(len(buf))
            )
            assert finder.marks_in_c(buf) == expected, buf.hex(" ")
            assert finder.marks_from_anchors(buf, buf.translate(table)) == expected, buf.hex(" ")


def test_marks_come_from_the_anchors_only_while_they_are_sparse() -> None:
    calls: list[str] = []

    class Counting(CandidateFinder):
        __slots__ = ()

        def marks_from_anchors(
            self, buf: bytes, anchors: bytes, most: int | None = None
        ) -> bytearray | None:
            marks = super().marks_from_anchors(buf, anchors, most)
            calls.append("anchors" if marks is not None else "too many anchors")
            return marks

        def marks_in_c(self, buf: bytes) -> bytes:
            calls.append("c")
            return super().marks_in_c(buf)

    finder = Counting((LA_REPLY_HEADER,), FF_REPLY)
    sparse = b"\xaa\x55" * 200 + b"\x01"  # headers everywhere, one CMD byte
    dense = b"\xaa\x55\x01\x01" * 100  # a CMD byte every other byte: seen at once
    dense_later = sparse + dense  # seen once the check has spent its budget
    assert finder.marks(sparse) == finder.marks_in_c(sparse)
    assert finder.marks(dense) == finder.marks_in_c(dense)
    assert finder.marks(dense_later) == finder.marks_in_c(dense_later)
    assert calls == ["anchors", "c", "c", "c", "too many anchors", "c", "c"]


@settings(max_examples=200)
@given(
    buf=streams,
    setup=st.sampled_from(SETUPS),
    expected=expectations,
    queries=st.lists(st.integers(0, 500), max_size=30),
)
def test_find_is_the_first_passing_header_at_or_after_a_position(
    buf: bytes,
    setup: tuple[Direction | None, tuple[Family, ...]],
    expected: tuple[FrameShape, ...] | None,
    queries: list[int],
) -> None:
    # Queries in any order: the index asks behind and ahead of the scan.
    judge = judge_for(setup, expected)
    finder = judge.finder
    passing = [p for p in header_positions(buf, judge.headers) if finder.passes(buf, p)]
    for pos in queries:
        want = next((p for p in passing if p >= pos), -1)
        assert finder.find(buf, pos) == want, (buf.hex(" "), pos)


def test_dense_junk_switches_to_the_marks_and_finds_the_frame_behind_it() -> None:
    status = la.encode_status(7, target=100, position=99)
    junk_run = b"\xaa\x55\xaa\x55\x55" * 40  # headers whose CMD byte is AA or 55
    r = Reassembler(families=(Family.LA,))
    items = r.feed(junk_run + status)
    assert items[-1] == Frame(Family.LA, Direction.REPLY, status)
    assert r.stats.discarded_bytes == len(junk_run)
    assert r.stats.by_reason == {"garbage": len(junk_run)}


def test_a_header_whose_command_byte_is_still_due_waits_for_it() -> None:
    status = la.encode_status(7, target=100, position=99)
    for cut_at in range(2, 6):
        r = Reassembler(families=(Family.LA,))
        assert r.feed(status[:cut_at]) == []
        assert r.feed(status[cut_at:]) == [Frame(Family.LA, Direction.REPLY, status)]


def test_changing_the_expectation_changes_what_an_ff_aa_header_must_show() -> None:
    reply = bytes.fromhex("ffaa01200000")  # byte 3 above 0x0F: no reply of the manuals
    r = Reassembler(families=(Family.PROJECT_STEPPER,))
    assert [type(i).__name__ for i in r.feed(reply)] == ["Discarded"]
    r.expect(ANY_REPLY)
    assert r.feed(reply) == [Frame(Family.PROJECT_STEPPER, Direction.REPLY, reply)]
