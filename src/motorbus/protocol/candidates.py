"""Where a frame may start: the reassembler's candidate headers, sorted out at C speed.

The reassembler judges each candidate header in Python (``protocol/frame_judge.py``), at
about a microsecond each.  Junk dense in header bytes (``AA 55 AA 55 ...``) holds a header
every few bytes, so judging them all costs hundreds of nanoseconds a byte, against a few
for junk that ``bytes.find`` skips.  Most such headers cannot start a frame whatever
follows them, because a byte the manuals fix does not fit (``protocol/frames.py``):

* an LA frame (``AA 55``, ``55 AA``): its CMD byte (byte 4) is one of the nine command
  codes, and unless it is a read or a write (01, 02) its Len (byte 2) is at most 0x2E;
* an ``FF AA`` request: byte 3 is at most 0x0F, unless byte 2 is the 0x8E opcode;
* an ``FF AA`` reply under the default expectation: byte 3 is at most 0x0F.  Under an
  explicit expectation (``Reassembler.expect``) every ``FF AA`` is a candidate: the
  shapes decide, in the judge, which discards what they refuse with its reason;
* ``EE DD``: always a candidate.

The judge applies the same rules, so what is skipped here is what it would refuse.  A
skipped header is part of the garbage around it.  A byte that has not arrived yet may be
anything: a header near the end of the buffer stays a candidate until its bytes come.

:class:`CandidateFinder` finds the next header that passes.  It starts with ``bytes.find``
and a check in Python per header; once a buffer has shown a few headers that fail
(``DENSE_AFTER``), it marks every passing position of the buffer at once, with C loops over
it (a byte-flag table, one big integer, a few shifts and ANDs), and from then on finds
each candidate with ``bytes.find`` in those marks.  Sans-I/O, pure.
"""

from __future__ import annotations

from motorbus.protocol.base import FF_AA, LA_REPLY_HEADER, LA_REQUEST_HEADER, PROJECT_FINISHED_BYTES
from motorbus.protocol.frames import (
    LA_ANY_LENGTH_COMMANDS,
    LA_COMMANDS,
    LA_MAX_LEN,
    LA_SHORT_MAX_LEN,
    STEPPER_B3_MAX,
    STEPPER_FREE_B3_OPCODE,
)

__all__ = [
    "DENSE_AFTER",
    "FF_ANY",
    "FF_REPLY",
    "FF_REQUEST",
    "CandidateFinder",
]

# What an ``FF AA`` header must show to be a candidate (``CandidateFinder.ff_rule``).
#: Anything (explicit reply shapes decide in the judge).
FF_ANY = 0
#: Byte 3 at most 0x0F (a reply under the default expectation).
FF_REPLY = 1
#: Byte 3 at most 0x0F, or byte 2 is 0x8E (a request, or either).
FF_REQUEST = 2

#: Headers that fail, in one buffer, before the finder marks the whole buffer at once.
DENSE_AFTER = 2
#: A header not searched for yet in the buffer: "searched from" beyond any position.
_UNSEARCHED = (1 << 62, -1)

# One flag bit per byte value the rules look at (EE DD has no rule: it is found apart).
_AA, _55, _FF, _LOW, _8E, _CMD, _ANY_LEN, _SHORT = (1 << i for i in range(8))
_FLAGS = bytes(
    (v == 0xAA) * _AA
    | (v == 0x55) * _55
    | (v == 0xFF) * _FF
    | (v <= STEPPER_B3_MAX) * _LOW
    | (v == STEPPER_FREE_B3_OPCODE) * _8E
    | (v in LA_COMMANDS) * _CMD
    | (v in LA_ANY_LENGTH_COMMANDS) * _ANY_LEN
    | (v <= LA_SHORT_MAX_LEN) * _SHORT
    for v in range(256)
)
#: Bytes past the end of the buffer: any value may still come, so every rule on a value
#: passes (no header byte does: a header must be there).
_PAD = bytes((_LOW | _8E | _CMD | _ANY_LEN | _SHORT,)) * 4


def _at(offset: int, flag: int) -> int:
    """The right shift that brings ``flag`` of the byte at ``p + offset`` to bit 0 of byte ``p``."""
    return 8 * offset + flag.bit_length() - 1


# The shifts of the rules (see ``_at``): a header's two bytes, LA Len and CMD, stepper
# bytes 2 and 3.
_AA_AT_1 = _at(1, _AA)
_55_AT_0, _55_AT_1 = _at(0, _55), _at(1, _55)
_FF_AT_0 = _at(0, _FF)
_CMD_AT_4, _ANY_LEN_AT_4, _SHORT_AT_2 = _at(4, _CMD), _at(4, _ANY_LEN), _at(2, _SHORT)
_LOW_AT_3, _8E_AT_2 = _at(3, _LOW), _at(2, _8E)


class CandidateFinder:
    """Finds, in one buffer after another, the next header that may start a frame.

    Args:
        headers: the headers the stream may carry (``FrameJudge.headers``).
        ff_rule: what an ``FF AA`` header must show (``FF_ANY``, ``FF_REPLY``,
            ``FF_REQUEST``); the judge sets it again when the expectation changes.
    """

    __slots__ = (
        "_buf",
        "_cache",
        "_ee_dd",
        "_ff_rule",
        "_marks",
        "_misses",
        "_ones",
        "_single",
        "headers",
    )

    def __init__(self, headers: tuple[bytes, ...], ff_rule: int) -> None:
        self.headers = headers
        self._ff_rule = ff_rule
        #: Index of ``EE DD`` in ``headers`` (found apart from the marks), or -1.
        self._ee_dd = (
            headers.index(PROJECT_FINISHED_BYTES) if PROJECT_FINISHED_BYTES in headers else -1
        )
        #: The only header, if there is one (one ``bytes.find``, no cache).
        self._single = headers[0] if len(headers) == 1 else None
        #: The buffer the cache and marks below are about (``None``: none yet).
        self._buf: bytes | None = None
        #: Per header: (searched from, found at or -1) in ``_buf``.
        self._cache = [_UNSEARCHED] * len(headers)
        self._marks: bytes | None = None
        self._misses = 0
        self._ones = (0, 0)

    @property
    def ff_rule(self) -> int:
        """What an ``FF AA`` header must show to be a candidate."""
        return self._ff_rule

    @ff_rule.setter
    def ff_rule(self, rule: int) -> None:
        if rule != self._ff_rule:
            self._ff_rule = rule
            self._buf = None  # what was found in the buffer was found by the old rule

    def find(self, buf: bytes, pos: int) -> int:
        """Position of the first candidate header at or after ``pos`` in ``buf``, or -1."""
        if buf is not self._buf:
            self._buf = buf
            self._cache = [_UNSEARCHED] * len(self.headers)
            self._marks = None
            self._misses = 0
        elif self._marks is not None:
            return self._in_marks(self._marks, buf, pos)
        single = self._single
        headers = self.headers
        cache = self._cache
        while True:
            if single is not None:
                p = buf.find(single, pos)
            else:
                # The first header at or after ``pos``: one ``bytes.find`` per header found,
                # not per call (a stream with several headers would search four times).
                p = -1
                for i, header in enumerate(headers):
                    since, q = cache[i]
                    if since > pos or 0 <= q < pos:
                        q = buf.find(header, pos)
                        cache[i] = (pos, q)
                    if q >= 0 and (p < 0 or q < p):
                        p = q
            if p < 0:
                return p
            # ``passes``, inline: this is the hot path of every frame.
            b0 = buf[p]
            if b0 == 0xAA or b0 == 0x55:
                if p + 4 >= len(buf) or buf[p + 2] <= LA_MAX_LEN[buf[p + 4]]:
                    return p
            elif (
                b0 != 0xFF
                or p + 3 >= len(buf)
                or buf[p + 3] <= STEPPER_B3_MAX
                or self._ff_rule == FF_ANY
                or (self._ff_rule == FF_REQUEST and buf[p + 2] == STEPPER_FREE_B3_OPCODE)
            ):
                return p
            self._misses += 1
            if self._misses >= DENSE_AFTER:
                marks = self._marks = self.marks(buf)
                return self._in_marks(marks, buf, p + 1)
            pos = p + 1

    def passes(self, buf: bytes, p: int) -> bool:
        """Does the header at ``p`` (one of ``headers``) pass the rules, in Python?"""
        n = len(buf)
        b0 = buf[p]
        if b0 == 0xFF:
            if p + 3 >= n:
                return True
            rule = self._ff_rule
            return (
                rule == FF_ANY
                or buf[p + 3] <= STEPPER_B3_MAX
                or (rule == FF_REQUEST and buf[p + 2] == STEPPER_FREE_B3_OPCODE)
            )
        if b0 == 0xEE:
            return True
        return p + 4 >= n or buf[p + 2] <= LA_MAX_LEN[buf[p + 4]]

    def marks(self, buf: bytes) -> bytes:
        """One byte per byte of ``buf``: 1 where an LA or ``FF AA`` candidate starts, else 0.

        Computed in C: each byte's flags (a translation table) become one integer, in
        which a shift by ``8 * offset + bit`` brings the flag of byte ``p + offset`` to
        bit 0 of byte ``p``; the rules are ANDs and ORs of such shifts.  (Only bit 0 of
        each byte is kept: the other bits of a result byte mean nothing.)
        """
        n = len(buf)
        flags = int.from_bytes(buf.translate(_FLAGS) + _PAD, "little")
        headers = self.headers
        la = 0
        if LA_REPLY_HEADER in headers:
            la = flags & (flags >> _55_AT_1)  # AA is flag bit 0 of byte p itself: no shift
        if LA_REQUEST_HEADER in headers:
            la |= (flags >> _55_AT_0) & (flags >> _AA_AT_1)
        if la:
            la &= (flags >> _CMD_AT_4) & ((flags >> _SHORT_AT_2) | (flags >> _ANY_LEN_AT_4))
        ff = 0
        if FF_AA in headers:
            ff = (flags >> _FF_AT_0) & (flags >> _AA_AT_1)
            if self._ff_rule == FF_REPLY:
                ff &= flags >> _LOW_AT_3
            elif self._ff_rule == FF_REQUEST:
                ff &= (flags >> _LOW_AT_3) | (flags >> _8E_AT_2)
        if self._ones[0] != n:
            self._ones = (n, int.from_bytes(b"\x01" * n, "little"))
        return ((la | ff) & self._ones[1]).to_bytes(n, "little")

    def _in_marks(self, marks: bytes, buf: bytes, pos: int) -> int:
        p = marks.find(1, pos)
        if self._ee_dd >= 0:
            q = self._next_ee_dd(buf, pos)
            if q >= 0 and (p < 0 or q < p):
                return q
        return p

    def _next_ee_dd(self, buf: bytes, pos: int) -> int:
        i = self._ee_dd
        since, q = self._cache[i]
        if since > pos or 0 <= q < pos:
            q = buf.find(PROJECT_FINISHED_BYTES, pos)
            self._cache[i] = (pos, q)
        return q
