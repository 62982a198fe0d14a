"""EchoFilter: our own output is removed from the received stream, nothing else is."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.transport import EchoFilter
from motorbus.transport.base import ECHO_BUFFER_MAX


def run(written: list[bytes], received: list[bytes]) -> tuple[list[bytes], int]:
    echo = EchoFilter()
    for w in written:
        echo.expect(w)
    out, removed = [], 0
    for chunk in received:
        rest, n = echo.feed(chunk)
        out.append(rest)
        removed += n
    return out, removed


@pytest.mark.parametrize(
    ("written", "received", "out", "removed"),
    [
        # nothing written: everything passes
        ([], [b"\xaa\x55"], [b"\xaa\x55"], 0),
        # whole echo, then the reply in the same chunk
        ([b"\x55\xaa\x03"], [b"\x55\xaa\x03\xaa\x55"], [b"\xaa\x55"], 3),
        # echo split over chunks, then the reply
        ([b"\x55\xaa\x03"], [b"\x55", b"\xaa", b"\x03\xaa"], [b"", b"", b"\xaa"], 3),
        # two writes echo as one stream
        ([b"\x01\x02", b"\x03"], [b"\x01\x02\x03\x04"], [b"\x04"], 3),
        # a mismatch ends echo matching: the rest passes, even bytes equal to our output
        ([b"\x01\x02\x03"], [b"\x01\x09\x02\x03"], [b"\x09\x02\x03"], 1),
        ([b"\x01\x02\x03"], [b"\x01\x09", b"\x02\x03"], [b"\x09", b"\x02\x03"], 1),
        # no echo at all (adapter without echo): the reply passes untouched
        ([b"\x01\x02"], [b"\x05\x06"], [b"\x05\x06"], 0),
    ],
)
def test_echo_table(
    written: list[bytes], received: list[bytes], out: list[bytes], removed: int
) -> None:
    assert run(written, received) == (out, removed)


def test_pending_counts_unechoed_bytes_and_reset_forgets_them() -> None:
    echo = EchoFilter()
    echo.expect(b"\x01\x02\x03")
    echo.feed(b"\x01")
    assert echo.pending == 2
    echo.reset()
    assert echo.pending == 0
    assert echo.feed(b"\x02\x03") == (b"\x02\x03", 0)


def test_expected_echo_is_bounded() -> None:
    echo = EchoFilter()
    echo.expect(bytes(ECHO_BUFFER_MAX) + b"\x01\x02")
    assert echo.pending == ECHO_BUFFER_MAX
    # The oldest bytes were forgotten: the newest still match.
    assert echo.feed(bytes(ECHO_BUFFER_MAX - 2) + b"\x01\x02\x07") == (b"\x07", ECHO_BUFFER_MAX)


@given(
    written=st.binary(min_size=1, max_size=40),
    reply=st.binary(max_size=40),
    cuts=st.lists(st.integers(0, 80), max_size=6),
)
def test_echo_then_reply_in_any_split_yields_the_reply(
    written: bytes, reply: bytes, cuts: list[int]
) -> None:
    stream = written + reply
    points = sorted({c for c in cuts if c <= len(stream)} | {0, len(stream)})
    chunks = [stream[a:b] for a, b in itertools.pairwise(points)]
    out, removed = run([written], chunks)
    assert b"".join(out) == reply
    assert removed == len(written)
