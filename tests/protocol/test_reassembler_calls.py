"""Work per byte of junk of every kind, counted by cProfile (calls, not time), at 64-byte and
4 KiB reads (issue 40; ``benchmarks/bench_reassembler.py`` times the same kinds).

Junk that no rule of ``protocol/rulebook.py`` lets start a frame is passed over in C, and
a flood of ``EE DD`` events is taken a run at a time: at most ``CHEAP_CALLS_PER_BYTE``.
Junk built to look like frames (right headers, lengths and command bytes, wrong checksums)
costs a verdict per header: at most ``CALLS_PER_HEADER`` calls for each.
"""

from __future__ import annotations

import cProfile
import pstats
import random

import pytest

from motorbus.protocol import la
from motorbus.protocol.base import Direction, Family, ProjectFinishedMarker, sum8
from motorbus.protocol.reassembler import Reassembler

SETUPS = {
    "la-bus": (Direction.REPLY, (Family.LA,)),
    "stepper-bus": (Direction.REPLY, (Family.PROJECT_STEPPER,)),
    "decode": (None, tuple(Family)),
    "simulator": (Direction.REQUEST, tuple(Family)),
}
READS = (64, 4096)
SIZE = 8000
#: Calls per byte fed for junk passed over in C (a 64-byte read costs ~15 calls whatever
#: its bytes, about 0.25 a byte; before issue 40 an ``EE DD`` flood cost 3.5).
CHEAP_CALLS_PER_BYTE = 1.0
#: Calls per header that reaches a verdict (a find, the verdict, its discarded runs, and
#: at small reads the index that judges it again when its bytes are in: ~40).
CALLS_PER_HEADER = 60


def _repeated(pattern: bytes) -> bytes:
    return (pattern * (SIZE // len(pattern) + 1))[:SIZE]


def _dense(pair: tuple[int, int], rng: random.Random) -> bytes:
    return bytes(
        rng.choice(pair) if rng.random() < 0.9 else rng.randrange(256) for _ in range(SIZE)
    )


CHEAP_KINDS = {
    "random": lambda rng: rng.randbytes(SIZE),
    "aa55-repeat": lambda rng: _repeated(b"\xaa\x55"),
    "55aa-repeat": lambda rng: _repeated(b"\x55\xaa"),
    "ffaa-repeat": lambda rng: _repeated(b"\xff\xaa"),
    "aa55-dense": lambda rng: _dense((0xAA, 0x55), rng),
    "ffaa-dense": lambda rng: _dense((0xFF, 0xAA), rng),
    "all-ff": lambda rng: b"\xff" * SIZE,
    "eedd-flood": lambda rng: _repeated(b"\xee\xdd"),
}


def _statuses(rng: random.Random) -> list[bytes]:
    return [
        la.encode_status(
            rng.randint(1, 254), target=rng.randint(0, 2000), position=rng.randint(0, 2000)
        )
        for _ in range(SIZE // la.STATUS_FRAME_SIZE)
    ]


def _requests(rng: random.Random) -> list[bytes]:
    out = []
    for _ in range(SIZE // 11):
        body = bytes((0xFF, 0xAA, rng.randint(1, 4), rng.randint(1, 15), *rng.randbytes(5), 3))
        out.append(body + bytes((sum8(body),)))
    return out


def _frame_like(kind: str, setup: str) -> tuple[bytes, int]:
    """Junk of ``kind`` for ``setup``, and how many headers in it reach a verdict."""
    rng = random.Random(kind + setup)
    frames = _requests(rng) if setup in ("simulator", "stepper-bus") else _statuses(rng)
    if kind == "bad-checksum":
        return b"".join(f[:-1] + bytes(((f[-1] + 1) & 0xFF,)) for f in frames), len(frames)
    if kind == "near-frames":
        return b"".join(f[:-1] for f in frames), len(frames)
    pattern = (
        b"\xff\xaa\x00\x01" if setup in ("simulator", "stepper-bus") else b"\xaa\x55\xff\x01\x01"
    )
    data = _repeated(pattern)
    return data, data.count(pattern[:2])


def calls(data: bytes, read: int, setup: str) -> tuple[int, Reassembler]:
    """cProfile's count of calls to feed ``data`` in ``read``-byte reads and end the stream,
    after a first pass unprofiled (one-time set-up is no work per byte)."""
    direction, families = SETUPS[setup]

    def run() -> Reassembler:
        r = Reassembler(direction=direction, families=families)
        for i in range(0, len(data), read):
            r.feed(data[i : i + read])
        r.end_of_stream()
        return r

    run()
    profiler = cProfile.Profile()
    r = profiler.runcall(run)
    total: int = pstats.Stats(profiler).total_calls  # type: ignore[attr-defined]
    return total, r


@pytest.mark.parametrize("read", READS)
@pytest.mark.parametrize("kind", sorted(CHEAP_KINDS))
@pytest.mark.parametrize("setup", sorted(SETUPS))
def test_junk_no_rule_lets_start_a_frame_costs_about_what_random_junk_does(
    setup: str, kind: str, read: int
) -> None:
    data = CHEAP_KINDS[kind](random.Random(kind))
    total, r = calls(data, read, setup)
    assert total / len(data) <= CHEAP_CALLS_PER_BYTE, (setup, kind, read, total / len(data))
    s = r.stats  # nothing skipped to save work: (almost) every byte is a discard or an event
    assert s.discarded_bytes + 2 * s.events >= len(data) - 6 * s.frames


@pytest.mark.parametrize("read", READS)
@pytest.mark.parametrize("setup", ["stepper-bus", "decode"])
def test_an_event_flood_is_every_event_at_a_few_calls_per_read(setup: str, read: int) -> None:
    data = _repeated(b"\xee\xdd")
    direction, families = SETUPS[setup]
    r = Reassembler(direction=direction, families=families)
    items = [item for i in range(0, len(data), read) for item in r.feed(data[i : i + read])]
    assert items == [ProjectFinishedMarker()] * (SIZE // 2)
    assert r.stats.events == SIZE // 2 and r.stats.discarded_bytes == 0
    total, _ = calls(data, read, setup)
    reads = -(-SIZE // read)
    assert total <= 30 * reads + 40, (total, reads)  # (40: ending the stream)


@pytest.mark.parametrize("read", READS)
@pytest.mark.parametrize("kind", ["bad-checksum", "near-frames", "plausible-headers"])
@pytest.mark.parametrize("setup", sorted(SETUPS))
def test_frame_like_junk_costs_a_bounded_number_of_calls_per_header(
    setup: str, kind: str, read: int
) -> None:
    data, headers = _frame_like(kind, setup)
    total, r = calls(data, read, setup)
    assert total <= CALLS_PER_HEADER * headers + 30 * -(-len(data) // read), (
        setup,
        kind,
        read,
        total / headers,
    )
    assert r.stats.discarded_bytes + r.stats.frames > 0
