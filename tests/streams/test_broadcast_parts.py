"""A tick's 0xF3 frames (``broadcast_parts`` and ``broadcast_builder``): every target once,
in order, at most 15 to a frame, and a frame rebuilt without a stream that stopped."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.protocol import la
from motorbus.protocol.la.wire import LA_REQUEST_HEADER, build_frame
from motorbus.streaming.model import broadcast_builder, broadcast_parts


@dataclass(eq=False)
class FakeStream:
    sending: bool = True


@st.composite
def ticks(draw: st.DrawFn) -> list[tuple[FakeStream, dict[int, int]]]:
    sizes = draw(st.lists(st.integers(1, 40), min_size=1, max_size=6))
    ids = iter(draw(st.permutations(range(1, 255))))
    return [
        (FakeStream(), {next(ids): draw(st.integers(0, 2000)) for _ in range(size)})
        for size in sizes
    ]


def byte_by_byte(entries: tuple[tuple[int, int], ...]) -> bytes:
    """The 0xF3 frame as the manual lays it out (3.5.3): ``55 AA``, the length, ``FF F3``
    and each entry's ID, position low byte and high byte, then the checksum."""
    body = [la.BROADCAST_ID, la.BroadcastMode.FOLLOW]
    for ident, pos in entries:
        body += [ident, pos & 0xFF, pos >> 8]
    return build_frame(LA_REQUEST_HEADER, bytes(body))


def test_a_frame_with_no_room_is_refused() -> None:
    with pytest.raises(ValueError, match="size=0 is out of range"):
        broadcast_parts([(FakeStream(), {1: 500})], 0)
    with pytest.raises(ValueError, match=r"size=16 is out of range: allowed 1\.\.15"):
        broadcast_parts([(FakeStream(), {1: 500})], 16)


@given(ticks(), st.integers(1, la.MAX_BROADCAST_ENTRIES))
def test_every_target_goes_once_in_order_and_no_frame_is_over_full(
    tick: list[tuple[FakeStream, dict[int, int]]], size: int
) -> None:
    frames = broadcast_parts(tick, size)
    sent = [pair for parts in frames for _, pairs in parts for pair in pairs]
    assert sent == [pair for _, targets in tick for pair in targets.items()]
    counts = [sum(len(pairs) for _, pairs in parts) for parts in frames]
    assert all(0 < n <= size for n in counts)
    assert all(n == size for n in counts[:-1])  # only the last frame may have room
    for parts in frames:
        frame = broadcast_builder(parts)()
        assert frame is not None
        assert frame.entries == tuple(pair for _, pairs in parts for pair in pairs)
        assert frame.encode() == byte_by_byte(frame.entries)


@given(ticks(), st.data())
def test_a_frame_is_rebuilt_without_the_streams_that_stopped(
    tick: list[tuple[FakeStream, dict[int, int]]], data: st.DataObject
) -> None:
    frames = broadcast_parts(tick, la.MAX_BROADCAST_ENTRIES)
    builds = [broadcast_builder(parts) for parts in frames]
    first = [build() for build in builds]
    assert [build() for build in builds] == first  # nothing stopped: the same frames
    stopped = data.draw(st.sets(st.sampled_from([s for s, _ in tick])))
    for s in stopped:
        s.sending = False
    for parts, build in zip(frames, builds, strict=True):
        left = tuple(pair for s, pairs in parts if s not in stopped for pair in pairs)
        frame = build()
        assert (frame.entries if frame is not None else ()) == left
