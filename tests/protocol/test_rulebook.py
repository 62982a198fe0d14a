"""The framing rulebook (``protocol/rulebook.py``): its rules, their lookups and checksums
agree, and a byte that has not arrived yet may be anything."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from motorbus.protocol import la
from motorbus.protocol.base import LA_REPLY_HEADER, sum8
from motorbus.protocol.rulebook import (
    ANYTHING,
    FF_REQUEST_ONLY,
    LA_MAX_LEN,
    LA_MAY,
    PROJECT_REQUEST_MAY,
    QUAD_REQUEST_MAY,
    at,
    both,
    either,
    ff_aa_rule,
    fits,
    la_claim,
    la_fits,
    la_sum_ok,
    request_sum_ok,
)


def test_the_la_lookup_is_the_la_rule() -> None:
    for cmd in range(256):
        for length in range(256):
            buf = bytes((0xAA, 0x55, length, 7, cmd))
            assert fits(LA_MAY, buf, 0) == (length <= LA_MAX_LEN[cmd]) == la_fits(buf, 0)


def test_a_byte_not_in_yet_may_be_anything() -> None:
    assert fits(LA_MAY, bytes((0xAA, 0x55, 0xFF, 7)), 0)  # CMD still due: Len FF may be a read
    assert not fits(LA_MAY, bytes((0xAA, 0x55, 0xFF, 7, 0x04)), 0)  # a status is short
    assert fits(ANYTHING, b"", 0) and not fits((), b"\xff\xaa", 0)
    assert la_claim(b"\xaa\x55", 0) == 0
    assert la_claim(b"\xaa\x55\x01", 0) == -1  # Len 1: no frame whatever follows
    assert la_claim(b"\xaa\x55\x11\x01\x04", 0) == 0x11 + 5


def test_terms_at_one_offset_merge_and_alternatives_are_kept_once() -> None:
    rule = both(at(2, range(10)), at(2, range(5, 20)))
    assert rule == at(2, range(5, 10))
    assert either(rule, rule, at(3, (1,))) == (rule[0], at(3, (1,))[0])


def test_a_request_only_stream_takes_a_request_of_either_stepper() -> None:
    rule = ff_aa_rule(FF_REQUEST_ONLY, quad=True, project=True)
    for b2, b3, b9 in (
        (0x03, 0x01, 0x0B),
        (0x05, 0x01, 0x0A),
        (0x8E, 0x40, 0x00),
        (0x05, 0x01, 0x0B),
    ):
        buf = bytes((0xFF, 0xAA, b2, b3, 0, 0, 0, 0, 0, b9))
        assert fits(rule, buf, 0) == (
            fits(QUAD_REQUEST_MAY, buf, 0) or fits(PROJECT_REQUEST_MAY, buf, 0)
        )
    assert not fits(ff_aa_rule(FF_REQUEST_ONLY, quad=False, project=False), b"\xff\xaa", 0)


@given(st.binary(min_size=2, max_size=255), st.binary(max_size=8))
def test_the_checksums_are_the_8_bit_sums(body: bytes, before: bytes) -> None:
    frame = la.build_frame(LA_REPLY_HEADER, body)
    buf = before + frame
    assert la_sum_ok(buf, len(before), len(buf))
    assert not la_sum_ok(buf[:-1] + bytes(((buf[-1] + 1) & 0xFF,)), len(before), len(buf))
    request = b"\xff\xaa" + body[:7]
    request += bytes((sum8(request),))
    assert request_sum_ok(before + request, len(before), len(request))
