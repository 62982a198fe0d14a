"""The framing rulebook: per family, its header, how long a frame is, what checks it, and
what a frame may be.

This is the one statement of the rules the reassembler cuts by.  Finding candidate headers
(``protocol/candidates.py``, which compiles the rules below to marks made in C) and judging
them (``protocol/frame_judge.py``) both read it; neither states a rule of its own.

=================  ==========  ============================  ===========================
family, direction  header      length                        checksum
=================  ==========  ============================  ===========================
LA request         ``55 AA``   Len (byte 2) + 5, Len >= 2    8-bit sum of bytes 2..end-1
LA reply           ``AA 55``   Len (byte 2) + 5, Len >= 2    8-bit sum of bytes 2..end-1
quad request       ``FF AA``   9                             8-bit sum of bytes 0..7
project request    ``FF AA``   11                            8-bit sum of bytes 0..9
stepper reply      ``FF AA``   6 (226 for the 0x3E dump)     none
project finished   ``EE DD``   2                             none
=================  ==========  ============================  ===========================

What a frame may be (docs/protocols.md A2-01, C.3, A.2; doc 000 A.2/A.4/A.5, doc 001
B.2/B.3) is a :data:`Rule`: which values a frame may carry at fixed offsets from its
header, as any of several conjunctions of ``(offset, table)`` terms (``table`` has 256
bytes, 1 where the value is allowed).  A byte that has not arrived yet may be anything:
a rule refuses a header only by bytes already in.  The rules: :data:`LA_MAY`,
:data:`QUAD_REQUEST_MAY`, :data:`PROJECT_REQUEST_MAY`, :data:`STEPPER_REPLY_MAY` (the
default expectation: ``Reassembler.expect`` replaces it by reply shapes); ``EE DD`` is
the whole event.  ``ff_aa_rule`` says which an ``FF AA`` header keeps on a stream.

Sans-I/O, pure data and a few functions.
"""

from __future__ import annotations

from collections.abc import Iterable
from zlib import adler32

from motorbus.protocol.base import FrameShape

__all__ = [
    "ANYTHING",
    "DUMP_SHAPE",
    "FF_ANY",
    "FF_REPLY",
    "FF_REQUEST",
    "FF_REQUEST_ONLY",
    "LA_ANY_LENGTH_COMMANDS",
    "LA_COMMANDS",
    "LA_MAX_FRAME",
    "LA_MAX_LEN",
    "LA_MAY",
    "LA_MIN_LEN",
    "LA_SHORT_MAX_LEN",
    "PROJECT_B9_MAX",
    "PROJECT_DUMP_SIZE",
    "PROJECT_REQUEST_MAY",
    "PROJECT_REQUEST_SIZE",
    "QUAD_ADDRESSES",
    "QUAD_REQUEST_MAY",
    "QUAD_REQUEST_SIZE",
    "REQUEST_B3_MAY",
    "STEPPER_B3_MAX",
    "STEPPER_FREE_B3_OPCODE",
    "STEPPER_REPLY_MAY",
    "STEPPER_REPLY_SHAPE",
    "STEPPER_REPLY_SIZE",
    "Rule",
    "ff_aa_rule",
    "fits",
    "la_claim",
    "la_fits",
    "la_sum_ok",
    "request_sum_ok",
]

# -- the facts ------------------------------------------------------------------------------

#: Longest LA frame: the Len byte is at most 255 and a frame is Len + 5 bytes (A2-01).
LA_MAX_FRAME = 255 + 5
#: Smallest valid LA Len: CMD and IDX with no data (a read request, Len 3, has one data byte;
#: a Len of 2 is the least a frame can say about itself).
LA_MIN_LEN = 2
#: The project stepper's parameter dump answering 0x3E (doc 000 A.5).
PROJECT_DUMP_SIZE = 226
#: Every stepper reply but the dump is 6 bytes (doc 000 A.2, doc 001 B.2).
STEPPER_REPLY_SIZE = 6
PROJECT_REQUEST_SIZE = 11  # doc 000 A.2
QUAD_REQUEST_SIZE = 9  # doc 001 B.2

#: The CMD byte (byte 4) of every LA frame is one of the nine command codes of doc 002
#: (docs/protocols.md C.3); a reply carries 01 (read), 02 (write ack), 04 (status) or
#: echoes its request's (A2-04).  The reassembler takes no LA frame with another CMD.
LA_COMMANDS = frozenset((0x01, 0x02, 0x03, 0x04, 0x19, 0x20, 0x21, 0xF2, 0xF3))
#: Reads and writes (CMD 01, 02) carry up to 253 table bytes: Len up to 255 (A2-01) ...
LA_ANY_LENGTH_COMMANDS = frozenset((0x01, 0x02))
#: ... every other frame is at most a 15-entry broadcast, Len 1 + 3 x 15 = 0x2E (a status
#: is Len 0x11, a motion request 4, a control request 3; C.3, C.4).
LA_SHORT_MAX_LEN = 0x2E
#: Byte 3 of every ``FF AA`` request and 6-byte reply the manuals define is at most 0x0F:
#: a motor command 01..0F, a project 1..4, a step-loop start 0..10, a value 0..2, an I/O
#: command 0B/0C, or 00 (doc 000 A.4, doc 001 B.3) ...
STEPPER_B3_MAX = 0x0F
#: ... but for one request: the project stepper's 0x8E, whose byte 3 is the repeat count
#: 0..255 (its reply, ``8E P 00 00``, keeps the rule).
STEPPER_FREE_B3_OPCODE = 0x8E
#: Byte 9 of every project request is the step, 1..10, or 00 (doc 000 A.2, A.4).
PROJECT_B9_MAX = 0x0A
#: Byte 2 of every quad request is an address: motor 1..4, 0x09 all motors, 0x00 I/O
#: (the LEDs) or 0xBC save (doc 001 B.2).
QUAD_ADDRESSES = frozenset((0x00, 0x01, 0x02, 0x03, 0x04, 0x09, 0xBC))

# -- rules: what a frame may be --------------------------------------------------------------

#: ``(offset from the header, table)``: the byte there must be one the table allows.
Term = tuple[int, bytes]
#: Any of these conjunctions of terms (``((),)`` allows anything, ``()`` nothing).
Rule = tuple[tuple[Term, ...], ...]

#: The rule that allows any bytes.
ANYTHING: Rule = ((),)
#: The table that allows any byte.
ANY_BYTE = bytes((1,)) * 256


def at(offset: int, allowed: Iterable[int]) -> Rule:
    """The byte at ``offset`` is one of ``allowed``."""
    values = frozenset(allowed)
    return (((offset, bytes(v in values for v in range(256))),),)


def either(*rules: Rule) -> Rule:
    """Any of ``rules``."""
    out: list[tuple[Term, ...]] = []
    for rule in rules:
        out += [c for c in rule if c not in out]
    return tuple(out)


def both(a: Rule, b: Rule) -> Rule:
    """``a`` and ``b`` (terms at one offset merge: the values both allow)."""
    out: list[tuple[Term, ...]] = []
    for ca in a:
        for cb in b:
            terms = dict(ca)
            for offset, table in cb:
                old = terms.get(offset, table)
                terms[offset] = bytes(x & y for x, y in zip(old, table, strict=True))
            conj = tuple(terms.items())
            if conj not in out:
                out.append(conj)
    return tuple(out)


def fits(rule: Rule, buf: bytes, p: int) -> bool:
    """Do the bytes of ``buf`` from ``p`` on keep ``rule`` (bytes not in yet may be anything)?"""
    n = len(buf)
    for conj in rule:
        for offset, table in conj:
            q = p + offset
            if q < n and not table[buf[q]]:
                break
        else:
            return True
    return False


#: An LA frame: a command code at byte 4, and a Len of at most 0x2E unless it reads or writes.
LA_MAY = either(
    both(at(4, LA_COMMANDS), at(2, range(LA_SHORT_MAX_LEN + 1))), at(4, LA_ANY_LENGTH_COMMANDS)
)
#: Per CMD byte, the largest Len ``LA_MAY`` allows with it (-1: none): the same rule as a
#: lookup, for the paths that judge one LA header at a time.
LA_MAX_LEN = tuple(
    max(
        (
            max((n for n in range(256) if dict(conj).get(2, ANY_BYTE)[n]), default=-1)
            for conj in LA_MAY
            if fits((tuple(t for t in conj if t[0] != 2),), bytes((0xAA, 0x55, 0, 0, cmd)), 0)
        ),
        default=-1,
    )
    for cmd in range(256)
)


def la_fits(buf: bytes, p: int) -> bool:
    """``fits(LA_MAY, buf, p)``, by ``LA_MAX_LEN``."""
    return p + 4 >= len(buf) or buf[p + 2] <= LA_MAX_LEN[buf[p + 4]]


#: Byte 3 of a 6-byte stepper reply (the default expectation).
STEPPER_REPLY_MAY = at(3, range(STEPPER_B3_MAX + 1))
#: Byte 3 of any ``FF AA`` request, of either stepper.
REQUEST_B3_MAY = either(STEPPER_REPLY_MAY, at(2, (STEPPER_FREE_B3_OPCODE,)))
#: A quad request: its byte 3, and an address at byte 2.
QUAD_REQUEST_MAY = both(REQUEST_B3_MAY, at(2, QUAD_ADDRESSES))
#: A project request: its byte 3, and a step (or 00) at byte 9.
PROJECT_REQUEST_MAY = both(REQUEST_B3_MAY, at(9, range(PROJECT_B9_MAX + 1)))

#: The dump answering 0x3E: ``FF AA 3E P 00 00`` and 220 bytes more.
DUMP_SHAPE = FrameShape.exact(PROJECT_DUMP_SIZE, 0xFF, 0xAA, 0x3E, frozenset(range(1, 5)), 0, 0)
#: Without an expectation, any 6-byte reply that keeps ``STEPPER_REPLY_MAY`` (after
#: ``DUMP_SHAPE``, with the project stepper: the reply shapes are tried in order).
STEPPER_REPLY_SHAPE = FrameShape.exact(
    STEPPER_REPLY_SIZE, 0xFF, 0xAA, None, frozenset(range(STEPPER_B3_MAX + 1))
)

# What an ``FF AA`` header must show, by what the stream may carry (``ff_aa_rule``).
#: Anything: explicit reply shapes decide, in the judge, which names its refusal.
FF_ANY = 0
#: A 6-byte reply under the default expectation.
FF_REPLY = 1
#: A reply or a request's byte 3 (``motorbus decode``: both directions).
FF_REQUEST = 2
#: A request of a stepper the stream may carry (a simulator: requests only).
FF_REQUEST_ONLY = 3


def ff_aa_rule(kind: int, *, quad: bool, project: bool) -> Rule:
    """The rule an ``FF AA`` header keeps on a stream of ``kind`` (``FF_ANY`` ...)."""
    if kind == FF_ANY:
        return ANYTHING
    if kind == FF_REPLY:
        return STEPPER_REPLY_MAY
    if kind == FF_REQUEST:
        return either(STEPPER_REPLY_MAY, REQUEST_B3_MAY)
    return either(
        *(r for r, on in ((QUAD_REQUEST_MAY, quad), (PROJECT_REQUEST_MAY, project)) if on)
    )


# -- lengths and checksums ------------------------------------------------------------------


def la_claim(buf: bytes, p: int) -> int:
    """Size the LA header at ``p`` claims: Len + 5; 0 if its Len is not in yet; -1 if it
    can be no frame whatever follows (Len below ``LA_MIN_LEN``, or ``LA_MAY`` broken)."""
    if len(buf) - p < 3:
        return 0
    length = buf[p + 2]
    if length < LA_MIN_LEN or (len(buf) - p >= 5 and length > LA_MAX_LEN[buf[p + 4]]):
        return -1
    return length + 5


def la_sum_ok(buf: bytes, p: int, end: int) -> bool:
    """Does the LA frame ``buf[p:end]`` carry the 8-bit sum of its bytes 2..end-1?

    Summed in C: ``adler32`` with a start value of 0 sums bytes modulo 65521, and 256
    bytes sum to at most 65280, so the sum of the first 256 is exact.
    """
    start, last = p + 2, end - 1
    if last - start <= 256:
        return adler32(buf[start:last], 0) & 0xFF == buf[last]
    return (adler32(buf[start : start + 256], 0) + sum(buf[start + 256 : last])) & 0xFF == buf[last]


def request_sum_ok(buf: bytes, p: int, size: int) -> bool:
    """Does the ``size``-byte stepper request at ``p`` carry the 8-bit sum of its bytes
    before it (in C, as ``la_sum_ok``)?"""
    end = p + size
    return adler32(buf[p : end - 1], 0) & 0xFF == buf[end - 1]
