"""The reassembler does bounded work per input byte, whatever the junk and however it is read.

Work is counted, not timed: every Python and C function call made while feeding (a
``sys.setprofile`` hook), divided by the bytes fed.  A resynchronisation that re-examines
the bytes it holds back at every read costs work in proportion to what it holds (up to a
whole 260-byte LA frame of candidate headers), not to what arrived; fed a byte at a time,
junk dense in ``AA 55`` headers then costs hundreds of calls per byte.
"""

from __future__ import annotations

import random
import sys
from types import FrameType

import pytest

from motorbus.protocol.base import Direction, Family
from motorbus.protocol.reassembler import Reassembler

#: Calls per byte fed.  Reading a byte at a time costs ~17 calls per read whatever the
#: bytes (the fixed cost of a ``feed``); the densest junk below costs up to ~110.
WORK_PER_BYTE = 160

SETUPS = {
    "la-bus": (Direction.REPLY, (Family.LA,)),
    "stepper-bus": (Direction.REPLY, (Family.PROJECT_STEPPER,)),
    "decode": (None, tuple(Family)),
    "simulator": (Direction.REQUEST, tuple(Family)),
}


def _dense(pair: tuple[int, int], size: int, rng: random.Random) -> bytes:
    return bytes(
        rng.choice(pair) if rng.random() < 0.9 else rng.randrange(256) for _ in range(size)
    )


def _junk(kind: str, size: int = 3000) -> bytes:
    rng = random.Random(kind)
    if kind == "random":
        return rng.randbytes(size)
    if kind == "aa55-dense":
        return _dense((0xAA, 0x55), size, rng)
    if kind == "ffaa-dense":
        return _dense((0xFF, 0xAA), size, rng)
    if kind == "all-ff":
        return b"\xff" * size
    if kind == "longest-la-headers":  # AA 55 FF: a header claiming 260 bytes every 3 bytes
        return b"\xaa\x55\xff" * (size // 3)
    if kind == "mixed-headers":
        return b"\xff\xaa\x55\xaa" * (size // 4)
    # Junk that passes the candidate prefilter (protocol/candidates.py): every header is
    # judged in Python.  A read reply (CMD 01) may claim 260 bytes; byte 3 of a request
    # is at most 0x0F.
    if kind == "plausible-la-headers":
        return b"\xaa\x55\xff\x01\x01" * (size // 5)
    if kind == "plausible-requests":
        return b"\xff\xaa\x00\x01" * (size // 4)
    raise AssertionError(kind)


def calls_per_byte(r: Reassembler, data: bytes, chunk: int) -> float:
    calls = 0

    def count(frame: FrameType, event: str, arg: object) -> None:
        nonlocal calls
        if event in ("call", "c_call"):
            calls += 1

    previous = sys.getprofile()
    sys.setprofile(count)
    try:
        for i in range(0, len(data), chunk):
            r.feed(data[i : i + chunk])
        r.end_of_stream()
    finally:
        sys.setprofile(previous)
    return calls / len(data)


@pytest.mark.parametrize("chunk", [1, 7, 4096])
@pytest.mark.parametrize(
    "kind",
    [
        "random",
        "aa55-dense",
        "ffaa-dense",
        "all-ff",
        "longest-la-headers",
        "mixed-headers",
        "plausible-la-headers",
        "plausible-requests",
    ],
)
@pytest.mark.parametrize("setup", sorted(SETUPS))
def test_work_per_byte_is_bounded_for_every_kind_of_junk(setup: str, kind: str, chunk: int) -> None:
    direction, families = SETUPS[setup]
    r = Reassembler(direction=direction, families=families)
    work = calls_per_byte(r, _junk(kind), chunk)
    assert work <= WORK_PER_BYTE, (
        f"{setup}: {kind} junk read {chunk} byte(s) at a time cost {work:.0f} calls per byte"
    )
    # Every byte is still accounted for: nothing was skipped to save work.
    s = r.stats
    assert s.discarded_bytes + s.events * 2 + r.buffered <= len(_junk(kind))


def test_work_does_not_grow_with_the_frame_a_header_claims() -> None:
    """Headers claiming 259-byte frames cost about what ones claiming 13 bytes cost.

    Every header here is a read reply's (CMD 01), which may be that long: each is judged.
    (A header claiming 7 bytes costs less: no later frame can fit in what follows it
    before its own frame is complete, so none is looked for.)
    """
    short = b"\xaa\x55\x08\x01\x01" * 600
    longest = b"\xaa\x55\xfe\x01\x01" * 600
    per_byte = {
        name: calls_per_byte(Reassembler(direction=None), data, 1)
        for name, data in (("short", short), ("longest", longest))
    }
    assert per_byte["longest"] <= 1.5 * per_byte["short"], per_byte
