"""The stream reassembler: framing, resync, events, bounds and accounting."""

from __future__ import annotations

import random

from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.protocol.base import Direction, Family, FrameShape, parse_hex, sum8
from motorbus.protocol.reassembler import (
    MAX_BUFFER,
    Discarded,
    Frame,
    Item,
    ProjectFinishedMarker,
    Reassembler,
)
from tests.vectors import load_vectors

STATUS = parse_hex("AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 00 01 08 07 0A 07 94")
READ_REPLY = parse_hex("AA 55 04 01 01 62 58 02 C2")
SHORT_ACK = parse_hex("AA 55 03 01 02 37 00 3D")


def la_reply(body: bytes) -> bytes:
    """An LA reply frame around ``body`` (ID CMD IDX data...); Len counts CMD..data."""
    length = len(body) - 1
    return b"\xaa\x55" + bytes([length]) + body + bytes([sum8(bytes([length]) + body)])


def frames_of(items: list[Item]) -> list[bytes]:
    return [i.raw for i in items if isinstance(i, Frame)]


def feed_all(r: Reassembler, chunks: list[bytes]) -> list[Item]:
    out: list[Item] = []
    for c in chunks:
        out += r.feed(c)
    return out


def accounted(r: Reassembler, items: list[Item]) -> int:
    return sum(len(i.raw) for i in items) + r.buffered


# -- document vectors ----------------------------------------------------------------


def test_every_la_document_request_is_framed_in_request_mode() -> None:
    vectors = [v for v in load_vectors() if v["device_kind"] == "inspire_la_55aa"]
    r = Reassembler(direction=Direction.REQUEST, families=[Family.LA])
    for v in vectors:
        raw = parse_hex(v.get("request_hex_corrected") or v["request_hex"])
        assert r.feed(raw) == [Frame(Family.LA, Direction.REQUEST, raw)], v["description"]


def test_v3_documented_checksum_28_is_refused() -> None:
    r = Reassembler(direction=Direction.REQUEST, families=[Family.LA])
    items = r.feed(parse_hex("55 AA 04 03 19 37 E8 03 28"))
    assert not frames_of(items)
    assert r.stats.by_reason.get("bad checksum") == 1
    # ... and the corrected frame (checksum 42) is accepted.
    good = parse_hex("55 AA 04 03 19 37 E8 03 42")
    assert frames_of(Reassembler(direction=Direction.REQUEST).feed(good)) == [good]


def test_every_stepper_document_request_is_framed() -> None:
    r = Reassembler(direction=Direction.REQUEST)
    for v in load_vectors():
        if v["device_kind"] == "inspire_la_55aa":
            continue
        raw = parse_hex(v["request_hex"])
        items = r.feed(raw)
        family = (
            Family.PROJECT_STEPPER if v["device_kind"].startswith("ffaa11") else Family.QUAD_STEPPER
        )
        assert items == [Frame(family, Direction.REQUEST, raw)], v["description"]


def test_la_replies_status_read_and_short_ack() -> None:
    r = Reassembler(families=[Family.LA])
    items = r.feed(STATUS + READ_REPLY + SHORT_ACK)
    assert frames_of(items) == [STATUS, READ_REPLY, SHORT_ACK]
    assert r.stats.frames == 3 and r.stats.discarded_bytes == 0


# -- resync ----------------------------------------------------------------------------


def test_garbage_before_between_and_after_is_discarded_and_counted() -> None:
    r = Reassembler(families=[Family.LA])
    items = r.feed(b"\x01\x02" + STATUS + b"\x03" + READ_REPLY + b"\x04\x05\x06")
    assert frames_of(items) == [STATUS, READ_REPLY]
    assert r.stats.discarded_bytes == 6
    assert all(i.reason == "garbage" for i in items if isinstance(i, Discarded))


def test_bad_checksum_costs_one_byte_and_next_frame_survives() -> None:
    bad = STATUS[:-1] + bytes([STATUS[-1] ^ 0xFF])
    r = Reassembler(families=[Family.LA])
    items = r.feed(bad + STATUS)
    assert frames_of(items) == [STATUS]
    assert r.stats.discarded_bytes == len(bad)


def test_header_claiming_a_long_frame_does_not_stall_a_valid_frame_behind_it() -> None:
    r = Reassembler(families=[Family.LA])
    items = r.feed(b"\xaa\x55\xf0" + STATUS)
    assert frames_of(items) == [STATUS]
    assert r.buffered == 0


def test_incomplete_frame_waits_for_its_bytes() -> None:
    r = Reassembler(families=[Family.LA])
    assert r.feed(STATUS[:10]) == []
    assert r.buffered == 10
    assert frames_of(r.feed(STATUS[10:])) == [STATUS]


def test_truncated_frame_at_end_of_stream_is_discarded() -> None:
    r = Reassembler(families=[Family.LA])
    r.feed(STATUS[:10])
    items = r.end_of_stream()
    assert items == [Discarded(STATUS[:10], "truncated frame")]


def test_buffer_is_bounded() -> None:
    r = Reassembler(families=[Family.LA], max_buffer=64)
    # An endless run of a header claiming a long frame with no valid frame after it.
    for _ in range(50):
        r.feed(b"\xaa\x55\xff" + bytes(40))
        assert r.buffered <= 64
    assert r.stats.discarded_bytes > 0


# -- steppers --------------------------------------------------------------------------


def test_ee_dd_between_stepper_frames_is_an_event() -> None:
    ack = parse_hex("FF AA 4E 01 00 00")
    r = Reassembler(families=[Family.PROJECT_STEPPER])
    items = r.feed(ack + b"\xee\xdd" + ack)
    assert items == [
        Frame(Family.PROJECT_STEPPER, Direction.REPLY, ack),
        ProjectFinishedMarker(),
        Frame(Family.PROJECT_STEPPER, Direction.REPLY, ack),
    ]
    assert r.stats.events == 1


def test_ee_dd_and_ff_aa_inside_the_226_byte_dump_are_data() -> None:
    dump = bytearray(parse_hex("FF AA 3E 02 00 00") + bytes(220))
    dump[50:52] = b"\xee\xdd"
    dump[100:106] = parse_hex("FF AA 6E 01 00 00")
    r = Reassembler(families=[Family.PROJECT_STEPPER])
    r.expect([FrameShape.exact(226, 0xFF, 0xAA, 0x3E, 0x02, 0, 0)])
    items = feed_all(r, [bytes(dump[i : i + 7]) for i in range(0, 226, 7)] + [b"\xee\xdd"])
    assert items == [
        Frame(Family.PROJECT_STEPPER, Direction.REPLY, bytes(dump)),
        ProjectFinishedMarker(),
    ]


def test_default_stepper_shapes_take_the_dump_whole() -> None:
    dump = parse_hex("FF AA 3E 01 00 00") + bytes(range(220))
    r = Reassembler(families=[Family.PROJECT_STEPPER])
    assert frames_of(r.feed(dump)) == [dump]


def test_expectation_refuses_look_alike_garbage_and_finds_the_real_reply() -> None:
    ack = parse_hex("FF AA 6E 01 00 00")
    r = Reassembler(families=[Family.PROJECT_STEPPER])
    r.expect([FrameShape.exact(6, 0xFF, 0xAA, 0x6E, 0x01, 0, 0)])
    items = r.feed(b"\xff\xaa\x01" + ack)
    assert frames_of(items) == [ack]
    assert r.stats.discarded_bytes == 3


def test_quad_done_reply_accepted_alongside_the_expected_ack() -> None:
    done = parse_hex("FF AA 00 09 01 00")
    ack = parse_hex("FF AA 09 06 00 00")
    r = Reassembler(families=[Family.QUAD_STEPPER])
    r.expect(
        [
            FrameShape.exact(6, 0xFF, 0xAA, 0x09, 0x06, 0, 0),
            FrameShape.exact(6, 0xFF, 0xAA, frozenset((0, 1)), 0x09, 1, 0),
        ]
    )
    assert frames_of(r.feed(done + ack)) == [done, ack]


def test_decode_mode_tells_requests_from_replies() -> None:
    stream = parse_hex(
        "FF AA 6E 01 01 00 00 00 00 00 19 FF AA 6E 01 00 00 EE DD "
        "55 AA 03 01 04 00 22 2A FF AA 09 06 00 00 00 00 B8 FF AA 09 06 00 00"
    )
    r = Reassembler(direction=None)
    items = r.feed(stream) + r.end_of_stream()
    kinds = [(i.family, i.direction) if isinstance(i, Frame) else type(i).__name__ for i in items]
    assert kinds == [
        (Family.PROJECT_STEPPER, Direction.REQUEST),
        (Family.PROJECT_STEPPER, Direction.REPLY),
        "ProjectFinishedMarker",
        (Family.LA, Direction.REQUEST),
        (Family.QUAD_STEPPER, Direction.REQUEST),
        (Family.QUAD_STEPPER, Direction.REPLY),
    ]


# -- properties ------------------------------------------------------------------------

la_bodies = st.one_of(
    st.builds(
        lambda i, data: bytes([i, 0x04, 0x00, 0x22]) + data,
        st.integers(1, 254),
        st.binary(min_size=15, max_size=15),
    ),
    st.builds(
        lambda i, idx, data: bytes([i, 0x01, idx]) + data,
        st.integers(1, 254),
        st.integers(0, 254),
        st.binary(min_size=1, max_size=4),
    ),
)
la_frames = st.lists(la_bodies.map(la_reply), min_size=1, max_size=12)


def split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    out, last = [], 0
    for p in points:
        out.append(data[last:p])
        last = p
    out.append(data[last:])
    return out


@given(frames=la_frames, cuts=st.lists(st.integers(0, 10_000), max_size=30))
def test_any_chunking_yields_the_same_frames(frames: list[bytes], cuts: list[int]) -> None:
    stream = b"".join(frames)
    whole = Reassembler(families=[Family.LA]).feed(stream)
    r = Reassembler(families=[Family.LA])
    chunked = feed_all(r, split(stream, cuts))
    assert frames_of(chunked) == frames_of(whole) == frames
    assert r.buffered == 0


@given(frames=la_frames, bytewise=st.booleans())
def test_byte_by_byte_equals_whole(frames: list[bytes], bytewise: bool) -> None:
    stream = b"".join(frames)
    r = Reassembler(families=[Family.LA])
    chunks = [stream[i : i + 1] for i in range(len(stream))] if bytewise else [stream]
    assert frames_of(feed_all(r, chunks)) == frames


# Garbage that cannot itself contain a header: with an 8-bit checksum, garbage that
# happens to hold "AA 55" plus a matching checksum is indistinguishable from a frame.
garbage = st.binary(max_size=12).filter(lambda g: b"\xaa\x55" not in g and not g.endswith(b"\xaa"))


@given(
    frames=la_frames,
    gaps=st.lists(garbage, min_size=13, max_size=13),
    cuts=st.lists(st.integers(0, 10_000), max_size=10),
)
def test_garbage_between_frames_never_loses_a_frame(
    frames: list[bytes], gaps: list[bytes], cuts: list[int]
) -> None:
    stream = b"".join(g + f for g, f in zip(gaps, frames, strict=False)) + gaps[-1]
    r = Reassembler(families=[Family.LA])
    items = feed_all(r, split(stream, cuts))
    assert frames_of(items) == frames
    assert accounted(r, items) == len(stream)
    assert r.stats.discarded_bytes == sum(len(g) for g in gaps[: len(frames)]) + len(gaps[-1]) - (
        r.buffered
    )


@given(
    frames=la_frames,
    victim=st.integers(0, 11),
    at=st.integers(0, 40),
    junk=st.binary(min_size=1, max_size=6).filter(lambda g: b"\xaa\x55" not in g),
)
def test_garbage_inside_a_frame_loses_only_that_frame(
    frames: list[bytes], victim: int, at: int, junk: bytes
) -> None:
    victim %= len(frames)
    damaged = list(frames)
    f = damaged[victim]
    cut = 3 + at % (len(f) - 3)  # after the header and length byte
    damaged[victim] = f[:cut] + junk + f[cut:]
    stream = b"".join(damaged)
    r = Reassembler(families=[Family.LA])
    got = frames_of(r.feed(stream) + r.end_of_stream())
    survivors = [fr for i, fr in enumerate(frames) if i != victim]
    # Every undamaged frame is there, in order (the damaged one may not be).
    it = iter(got)
    assert all(any(g == s for g in it) for s in survivors)


@settings(max_examples=300)
@given(data=st.binary(max_size=600), cuts=st.lists(st.integers(0, 10_000), max_size=20))
def test_random_bytes_never_raise_and_every_byte_is_accounted(data: bytes, cuts: list[int]) -> None:
    for direction in (Direction.REPLY, Direction.REQUEST, None):
        r = Reassembler(direction=direction)
        items = feed_all(r, split(data, cuts))
        assert r.buffered <= MAX_BUFFER
        assert accounted(r, items) == len(data)
        items += r.end_of_stream()
        assert sum(len(i.raw) for i in items) == len(data)


def test_seeded_random_splits_of_mixed_stepper_replies() -> None:
    rng = random.Random(7)
    acks = [parse_hex(h) for h in ("FF AA 6E 01 00 00", "FF AA 03 03 00 01", "FF AA 00 0B 01 01")]
    stream = b"".join(
        rng.choice(acks) + (b"\xee\xdd" if rng.random() < 0.3 else b"") for _ in range(200)
    )
    whole = Reassembler(families=[Family.PROJECT_STEPPER]).feed(stream)
    cuts = [rng.randrange(len(stream)) for _ in range(80)]
    r = Reassembler(families=[Family.PROJECT_STEPPER])
    assert feed_all(r, split(stream, cuts)) == whole
