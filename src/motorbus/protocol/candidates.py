"""Where a frame may start: the reassembler's candidate headers, sorted out at C speed.

The reassembler judges each candidate header in Python (``protocol/frame_judge.py``), at
about a microsecond each.  Junk dense in header bytes (``AA 55 AA 55 ...``) holds a header
every few bytes, so judging them all costs hundreds of nanoseconds a byte, against a few
for junk that ``bytes.find`` skips.  Most such headers cannot start a frame whatever
follows them, because a byte the manuals fix does not fit (``protocol/frames.py``):

* an LA frame (``AA 55``, ``55 AA``): its CMD byte (byte 4) is one of the nine command
  codes, and unless it is a read or a write (01, 02) its Len (byte 2) is at most 0x2E;
* an ``FF AA`` request: byte 3 is at most 0x0F, unless byte 2 is the 0x8E opcode; on
  a stream of requests only (``FF_REQUEST_ONLY``), byte 2 is also a quad address or
  byte 9 a project step (``frames.QUAD_ADDRESSES``, ``frames.PROJECT_B9_MAX``);
* an ``FF AA`` reply under the default expectation: byte 3 is at most 0x0F.  Under an
  explicit expectation (``Reassembler.expect``) every ``FF AA`` is a candidate: the
  shapes decide, in the judge, which discards what they refuse with its reason;
* ``EE DD``: always a candidate.

The judge applies the same rules, so what is skipped here is what it would refuse.  A
skipped header is part of the garbage around it.  A byte that has not arrived yet may be
anything: a header near the end of the buffer stays a candidate until its bytes come.

:class:`CandidateFinder` finds the next header that passes.  It starts with ``bytes.find``
and a check in Python per header; once a buffer has shown a few headers that fail
(``DENSE_AFTER``), it marks every passing position of the buffer at once and from then on
finds each candidate with ``bytes.find`` in those marks.  It marks in one of two ways,
whichever is cheaper for the buffer at hand:

* **from the anchors**: every rule fixes one byte after the header (an LA frame's CMD, an
  ``FF AA`` frame's byte 3, or byte 2 for the 0x8E request), and junk dense in headers is
  seldom dense in those bytes too.  A translation table finds them in C; each is checked
  in Python against the header before it.  Used when anchors are at most one byte in
  ``2 ** ANCHOR_SHIFT``;
* **in C throughout**: each byte's flags become one big integer, and the rules are a few
  shifts and ANDs over it: a fixed cost per byte, however dense the anchors are.

Either way the work per byte is bounded.  Sans-I/O, pure.
"""

from __future__ import annotations

from motorbus.protocol.base import FF_AA, LA_REPLY_HEADER, LA_REQUEST_HEADER, PROJECT_FINISHED_BYTES
from motorbus.protocol.frames import (
    LA_ANY_LENGTH_COMMANDS,
    LA_COMMANDS,
    LA_MAX_LEN,
    LA_SHORT_MAX_LEN,
    PROJECT_B9_MAX,
    QUAD_ADDRESSES,
    STEPPER_B3_MAX,
    STEPPER_FREE_B3_OPCODE,
)

__all__ = [
    "ANCHOR_SHIFT",
    "DENSE_AFTER",
    "FF_ANY",
    "FF_REPLY",
    "FF_REQUEST",
    "FF_REQUEST_ONLY",
    "CandidateFinder",
]

# What an ``FF AA`` header must show to be a candidate (``CandidateFinder.ff_rule``).
#: Anything (explicit reply shapes decide in the judge).
FF_ANY = 0
#: Byte 3 at most 0x0F (a reply under the default expectation).
FF_REPLY = 1
#: Byte 3 at most 0x0F, or byte 2 is 0x8E (a request or a reply: ``motorbus decode``).
FF_REQUEST = 2
#: ``FF_REQUEST``, and byte 2 a quad address or byte 9 a project step (a request only).
FF_REQUEST_ONLY = 3

#: Headers that fail, in one buffer, before the finder marks the whole buffer at once
#: (one, if the buffer before was marked).
DENSE_AFTER = 2
#: Marks come from the anchors when they are at most one byte in ``2 ** ANCHOR_SHIFT``:
#: a Python check per anchor (~0.15 us) against ~3 ns per byte in C
#: (benchmarks/bench_reassembler.py).
ANCHOR_SHIFT = 5
#: Bytes at the start of a buffer whose anchors are counted before checking any.
_PROBE = 256
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
# The request-only rule's flags, in a second table (the first has no bit left).
_QUAD_ADDRESS, _STEP = 1, 2
_REQUEST_FLAGS = bytes(
    (v in QUAD_ADDRESSES) * _QUAD_ADDRESS | (v <= PROJECT_B9_MAX) * _STEP for v in range(256)
)
_REQUEST_PAD = bytes((_QUAD_ADDRESS | _STEP,)) * 10


def _anchor_table_for(la: bool, ff: bool, ff_8e: bool) -> bytes:
    """1 for each byte value that anchors a rule: an LA CMD, an ``FF AA`` byte 3, 0x8E."""
    return bytes(
        (la and v in LA_COMMANDS)
        or (ff and v <= STEPPER_B3_MAX)
        or (ff_8e and v == STEPPER_FREE_B3_OPCODE)
        for v in range(256)
    )


#: The anchor tables, by (LA headers?, ``FF AA``?, its 0x8E rule?): built once, not per
#: reassembler (a bus makes one per connection, the simulator one per request).
_ANCHOR_TABLES = {
    (la, ff, ff_8e): _anchor_table_for(la, ff, ff_8e)
    for la in (False, True)
    for ff in (False, True)
    for ff_8e in (False, True)
}


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
_QUAD_ADDRESS_AT_2, _STEP_AT_9 = _at(2, _QUAD_ADDRESS), _at(9, _STEP)


class CandidateFinder:
    """Finds, in one buffer after another, the next header that may start a frame.

    Args:
        headers: the headers the stream may carry (``FrameJudge.headers``).
        ff_rule: what an ``FF AA`` header must show (``FF_ANY``, ``FF_REPLY``,
            ``FF_REQUEST``, ``FF_REQUEST_ONLY``); the judge sets it again when the
            expectation changes.
        quad, project: whether the stream may carry requests of that stepper (for
            ``FF_REQUEST_ONLY``).
    """

    __slots__ = (
        "_anchors",
        "_buf",
        "_cache",
        "_ee_dd",
        "_ff_rule",
        "_marked_headers",
        "_marks",
        "_misses",
        "_ones",
        "_project",
        "_quad",
        "_rules",
        "_single",
        "headers",
    )

    def __init__(
        self, headers: tuple[bytes, ...], ff_rule: int, *, quad: bool = True, project: bool = True
    ) -> None:
        self.headers = headers
        self._ff_rule = ff_rule
        self._quad = quad
        self._project = project
        #: Index of ``EE DD`` in ``headers`` (marked apart from the rules), or -1.
        self._ee_dd = (
            headers.index(PROJECT_FINISHED_BYTES) if PROJECT_FINISHED_BYTES in headers else -1
        )
        #: The only header, if there is one (one ``bytes.find``, no cache).
        self._single = headers[0] if len(headers) == 1 else None
        #: The buffer the cache and marks below are about (``None``: none yet).
        self._buf: bytes | None = None
        #: Per header: (searched from, found at or -1) in ``_buf``.
        self._cache = [_UNSEARCHED] * len(headers)
        self._marks: bytes | bytearray | None = None
        self._misses = 0
        self._ones = (0, 0)
        self._anchors = self._anchor_table()
        self._rules = self._rules_now()
        #: The headers the marks show (``EE DD`` is found apart), each with how far from
        #: its anchor it starts: one that starts this close to the end passes the rules.
        self._marked_headers = tuple(
            (h, 3 if h == FF_AA else 4) for h in headers if h != PROJECT_FINISHED_BYTES
        )

    @property
    def ff_rule(self) -> int:
        """What an ``FF AA`` header must show to be a candidate."""
        return self._ff_rule

    @ff_rule.setter
    def ff_rule(self, rule: int) -> None:
        if rule != self._ff_rule:
            self._ff_rule = rule
            self._buf = None  # what was found in the buffer was found by the old rule
            self._anchors = self._anchor_table()
            self._rules = self._rules_now()

    def find(self, buf: bytes, pos: int) -> int:
        """Position of the first candidate header at or after ``pos`` in ``buf``, or -1."""
        if buf is self._buf:
            if self._marks is not None:
                return self._marks.find(1, pos)
        else:
            self._buf = buf
            if self._single is None:
                self._cache = [_UNSEARCHED] * len(self.headers)
            # Junk comes in runs: after a marked buffer, one failing header marks the next.
            self._misses = DENSE_AFTER - 1 if self._marks is not None else 0
            self._marks = None
        single = self._single
        headers = self.headers
        cache = self._cache
        n = len(buf)
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
                if p + 4 >= n or buf[p + 2] <= LA_MAX_LEN[buf[p + 4]]:
                    return p
            elif b0 != 0xFF:
                return p  # EE DD
            elif (
                p + 3 >= n
                or buf[p + 3] <= STEPPER_B3_MAX
                or self._ff_rule == FF_ANY
                or (self._ff_rule >= FF_REQUEST and buf[p + 2] == STEPPER_FREE_B3_OPCODE)
            ) and (
                self._ff_rule != FF_REQUEST_ONLY
                or (self._quad and (p + 2 >= n or buf[p + 2] in QUAD_ADDRESSES))
                or (self._project and (p + 9 >= n or buf[p + 9] <= PROJECT_B9_MAX))
            ):
                return p  # ``request_fits``, inline: every request of a simulator
            self._misses += 1
            if self._misses >= DENSE_AFTER:
                marks = self._marks = self._all_marks(buf)
                return marks.find(1, p + 1)
            pos = p + 1

    def passes(self, buf: bytes, p: int) -> bool:
        """Does the header at ``p`` (one of ``headers``) pass the rules, in Python?"""
        n = len(buf)
        b0 = buf[p]
        if b0 == 0xFF:
            rule = self._ff_rule
            return (
                p + 3 >= n
                or rule == FF_ANY
                or buf[p + 3] <= STEPPER_B3_MAX
                or (rule >= FF_REQUEST and buf[p + 2] == STEPPER_FREE_B3_OPCODE)
            ) and (rule != FF_REQUEST_ONLY or self.request_fits(buf, p))
        if b0 == 0xEE:
            return True
        return p + 4 >= n or buf[p + 2] <= LA_MAX_LEN[buf[p + 4]]

    def request_fits(self, buf: bytes, p: int) -> bool:
        """May the ``FF AA`` at ``p`` be a quad request (byte 2 an address) or a project
        one (byte 9 a step)?  A byte not yet in ``buf`` may be anything."""
        n = len(buf)
        return (self._quad and (p + 2 >= n or buf[p + 2] in QUAD_ADDRESSES)) or (
            self._project and (p + 9 >= n or buf[p + 9] <= PROJECT_B9_MAX)
        )

    def marks(self, buf: bytes) -> bytes | bytearray:
        """One byte per byte of ``buf``: 1 where an LA or ``FF AA`` candidate starts, else 0.

        From the anchors when they are sparse enough, else in C throughout (see the
        module docstring); the two agree byte for byte.
        """
        table = self._anchors
        if table is not None:
            anchors = buf.translate(table)
            # A first look at the density: random junk is dense in anchors, and checking
            # ``2 ** -ANCHOR_SHIFT`` of its bytes before giving up would be waste.
            if anchors.count(1, 0, _PROBE) <= _PROBE >> ANCHOR_SHIFT:
                marks = self.marks_from_anchors(buf, anchors, len(buf) >> ANCHOR_SHIFT)
                if marks is not None:
                    return marks
        return self.marks_in_c(buf)

    def marks_from_anchors(
        self, buf: bytes, anchors: bytes, most: int | None = None
    ) -> bytearray | None:
        """``marks``, from the anchor bytes (1 in ``anchors``, ``buf`` translated by
        ``_anchor_table``): each is checked against the header it would complete.

        ``None`` once more than ``most`` anchors have come (``marks_in_c`` is cheaper
        then): the work spent is bounded by ``most`` checks.
        """
        n = len(buf)
        budget = n if most is None else most
        marks = bytearray(n)
        la_reply, la_request, ff, ff_8e, request_only = self._rules
        request_fits = self.request_fits
        max_len = LA_MAX_LEN
        find = anchors.find
        q = find(1)
        while q >= 0:
            budget -= 1
            if budget < 0:
                return None
            v = buf[q]
            p = q - 4
            if p >= 0 and buf[p + 2] <= max_len[v]:
                b0, b1 = buf[p], buf[p + 1]
                if (la_reply and b0 == 0xAA and b1 == 0x55) or (
                    la_request and b0 == 0x55 and b1 == 0xAA
                ):
                    marks[p] = 1
            if ff:
                if v <= STEPPER_B3_MAX:
                    p = q - 3
                else:
                    p = q - 2 if ff_8e and v == STEPPER_FREE_B3_OPCODE else -1
                if (
                    p >= 0
                    and buf[p] == 0xFF
                    and buf[p + 1] == 0xAA
                    and (not request_only or request_fits(buf, p))
                ):
                    marks[p] = 1
            q = find(1, q + 1)
        # Headers whose anchor has not arrived yet: the rules pass them (``passes``).
        for header, due in self._marked_headers:
            p = buf.find(header, n - due if n > due else 0)
            while p >= 0:
                if header != FF_AA or not request_only or request_fits(buf, p):
                    marks[p] = 1
                p = buf.find(header, p + 1)
        return marks

    def marks_in_c(self, buf: bytes) -> bytes:
        """``marks``, in C throughout: each byte's flags (a translation table) become
        one integer, in which a shift by ``8 * offset + bit`` brings the flag of byte
        ``p + offset`` to bit 0 of byte ``p``; the rules are ANDs and ORs of such shifts.
        (Only bit 0 of each byte is kept: the other bits of a result byte mean nothing.)
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
            elif self._ff_rule >= FF_REQUEST:
                ff &= (flags >> _LOW_AT_3) | (flags >> _8E_AT_2)
            if self._ff_rule == FF_REQUEST_ONLY and ff:
                ff &= self._requests_in_c(buf)
        if self._ones[0] != n:
            self._ones = (n, int.from_bytes(b"\x01" * n, "little"))
        return ((la | ff) & self._ones[1]).to_bytes(n, "little")

    def _requests_in_c(self, buf: bytes) -> int:
        """Bit 0 of byte ``p`` set where an ``FF AA`` at ``p`` may be a request by byte 2
        (a quad address) or byte 9 (a project step), as ``marks_in_c`` combines them."""
        flags = int.from_bytes(buf.translate(_REQUEST_FLAGS) + _REQUEST_PAD, "little")
        fits = 0
        if self._quad:
            fits = flags >> _QUAD_ADDRESS_AT_2
        if self._project:
            fits |= flags >> _STEP_AT_9
        return fits

    def _rules_now(self) -> tuple[bool, bool, bool, bool, bool]:
        """Which rules ``marks_from_anchors`` applies: LA replies, LA requests, ``FF AA``,
        its 0x8E exception, its request-only rule."""
        headers = self.headers
        ff = FF_AA in headers
        return (
            LA_REPLY_HEADER in headers,
            LA_REQUEST_HEADER in headers,
            ff,
            ff and self._ff_rule >= FF_REQUEST,
            self._ff_rule == FF_REQUEST_ONLY,
        )

    def _anchor_table(self) -> bytes | None:
        """Translation table: 1 for a byte that may anchor a candidate, else 0; ``None``
        when some header has no anchor (``FF AA`` under ``FF_ANY``)."""
        headers = self.headers
        ff = FF_AA in headers
        if ff and self._ff_rule == FF_ANY:
            return None
        la = LA_REPLY_HEADER in headers or LA_REQUEST_HEADER in headers
        return _ANCHOR_TABLES[la, ff, ff and self._ff_rule >= FF_REQUEST]

    def _all_marks(self, buf: bytes) -> bytes | bytearray:
        """``marks``, plus every ``EE DD`` when it is one of the headers."""
        marks = self.marks(buf)
        if self._ee_dd >= 0:
            q = buf.find(PROJECT_FINISHED_BYTES)
            if q >= 0:
                marks = bytearray(marks)
                while q >= 0:
                    marks[q] = 1
                    q = buf.find(PROJECT_FINISHED_BYTES, q + 1)
        return marks
