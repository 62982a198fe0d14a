"""Where a frame may start: the rulebook's rules, compiled to marks made in C.

The judge (``protocol/frame_judge.py``) costs about a microsecond per candidate header, and
junk dense in header bytes (``AA 55 AA 55 ...``) holds a header every few bytes.  Most such
headers break a rule of ``protocol/rulebook.py`` (what a frame may be) whatever follows
them; :class:`CandidateFinder` passes over those as garbage, and the judge, reading the same
rules, would refuse them.  A byte that has not arrived yet may be anything: a header near
the end of the buffer stays a candidate until its bytes come.

It starts with ``bytes.find`` and ``rulebook.fits`` per header; once a buffer has shown a
few headers that fail (``DENSE_AFTER``), it marks every passing position of the buffer at
once and from then on finds each candidate with ``bytes.find`` in those marks.  It marks in
one of two ways, whichever is cheaper for the buffer at hand:

* **from the anchors**: the first term of each conjunction of a rule (an LA frame's CMD, an
  ``FF AA`` frame's byte 3, or byte 2 for the 0x8E request) is its anchor, and junk dense in
  headers is seldom dense in those bytes too.  A translation table finds them in C; each is
  checked in Python against the header before it.  Used when anchors are at most one byte
  in ``2 ** ANCHOR_SHIFT``;
* **in C throughout**: each byte's flags (one bit per table of the rules) become one big
  integer, and the rules are shifts, ANDs and ORs over it: a fixed cost per byte.

Either way the work per byte is bounded.  Sans-I/O, pure.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache, partial
from typing import NamedTuple

from motorbus.protocol.base import FF_AA, PROJECT_FINISHED_BYTES
from motorbus.protocol.rulebook import (
    ANYTHING,
    FF_ANY,
    FF_REPLY,
    FF_REQUEST,
    FF_REQUEST_ONLY,
    LA_MAX_LEN,
    LA_MAY,
    Rule,
    ff_aa_rule,
    fits,
    la_fits,
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

#: Headers that fail, in one buffer, before the finder marks the whole buffer at once
#: (one, if the buffer before was marked).
DENSE_AFTER = 2
#: Marks come from the anchors when they are at most one byte in ``2 ** ANCHOR_SHIFT``:
#: a Python check per anchor (~0.3 us) against a few ns per byte in C
#: (benchmarks/bench_reassembler.py).
ANCHOR_SHIFT = 5
#: Bytes at the start of a buffer whose anchors are counted before checking any.
_PROBE = 256
#: A header not searched for yet in the buffer: "searched from" beyond any position.
_UNSEARCHED = (1 << 62, -1)

#: A term compiled for ``marks_in_c``: (flag group, right shift bringing its flag to bit 0).
_Shift = tuple[int, int]


class _Program(NamedTuple):
    """The rules of one set-up, compiled (``_compile``)."""

    #: By a header's first byte, a check of the rule it keeps.
    checks: tuple[Callable[[bytes, int], bool], ...]
    #: Per flag group: (translation table to flag bits, pad for bytes not in yet).
    groups: tuple[tuple[bytes, bytes], ...]
    #: Per marked header: its two bytes' shifts, and each conjunction's.
    marked: tuple[tuple[tuple[_Shift, ...], tuple[tuple[_Shift, ...], ...]], ...]
    #: 1 for a byte value that anchors a conjunction; ``None`` if one has no anchor.
    anchors: bytes | None
    #: By anchor value: (header, the anchor's offset, the conjunction it anchors, as a rule).
    by_anchor: tuple[tuple[tuple[bytes, int, Rule], ...], ...]
    #: (header, its rule, how far from its farthest anchor it starts).
    tails: tuple[tuple[bytes, Rule, int], ...]


@lru_cache(maxsize=64)
def _compile(headers: tuple[bytes, ...], ff_rule: int, quad: bool, project: bool) -> _Program:
    """Compile the rules of ``headers`` (built once per set-up, not per reassembler)."""

    def rule_of(h: bytes) -> Rule:
        if h == PROJECT_FINISHED_BYTES:
            return ANYTHING
        return ff_aa_rule(ff_rule, quad=quad, project=project) if h == FF_AA else LA_MAY

    checks: list[Callable[[bytes, int], bool]] = [partial(fits, ())] * 256
    for h in headers:
        checks[h[0]] = la_fits if rule_of(h) is LA_MAY else partial(fits, rule_of(h))
    marked = [(h, rule_of(h)) for h in headers if h != PROJECT_FINISHED_BYTES]
    # One flag bit per table (a header byte's, or a rule's), eight to a group.
    slots: dict[tuple[bytes, bool], int] = {}

    def shift(offset: int, table: bytes, header: bool = False) -> _Shift:
        i = slots.setdefault((table, header), len(slots))
        return i >> 3, 8 * offset + (i & 7)

    program = tuple(
        (
            tuple(shift(o, bytes(v == b for v in range(256)), True) for o, b in enumerate(h)),
            tuple(tuple(shift(o, t) for o, t in conj) for conj in rule),
        )
        for h, rule in marked
    )
    groups = []
    for g in range((len(slots) + 7) >> 3):
        table, pad = bytes(256), 0
        for (t, header), i in slots.items():
            if i >> 3 == g:
                table = bytes(x | y << (i & 7) for x, y in zip(table, t, strict=True))
                pad |= 0 if header else 1 << (i & 7)
        groups.append((table, bytes((pad,)) * 10))
    # Anchors: the first term of each conjunction.
    by_anchor: list[list[tuple[bytes, int, Rule]]] = [[] for _ in range(256)]
    for h, rule in marked:
        for conj in (c for c in rule if c):
            offset, allowed = conj[0]
            for v in range(256):
                if allowed[v]:
                    by_anchor[v].append((h, offset, (conj,)))
    anchored = all(conj for _, rule in marked for conj in rule)
    return _Program(
        checks=tuple(checks),
        groups=tuple(groups),
        marked=program,
        anchors=bytes(bool(a) for a in by_anchor) if anchored else None,
        by_anchor=tuple(tuple(a) for a in by_anchor),
        tails=tuple((h, rule, max((c[0][0] for c in rule if c), default=0)) for h, rule in marked),
    )


class CandidateFinder:
    """Finds, in one buffer after another, the next header that may start a frame.

    Args:
        headers: the headers the stream may carry (``FrameJudge.headers``).
        ff_rule: what an ``FF AA`` header must keep (``rulebook.FF_ANY`` ...); the judge
            sets it again when the expectation changes.
        quad, project: whether the stream may carry requests of that stepper (for
            ``FF_REQUEST_ONLY``).
    """

    __slots__ = (
        "_buf",
        "_cache",
        "_ee_dd",
        "_ff_rule",
        "_marks",
        "_misses",
        "_ones",
        "_program",
        "_project",
        "_quad",
        "_single",
        "headers",
    )

    def __init__(
        self, headers: tuple[bytes, ...], ff_rule: int, *, quad: bool = True, project: bool = True
    ) -> None:
        self.headers = headers
        self._quad = quad
        self._project = project
        self._ff_rule = ff_rule
        self._program = _compile(headers, ff_rule, quad, project)
        #: Whether ``EE DD`` is one of the headers (marked apart from the rules).
        self._ee_dd = PROJECT_FINISHED_BYTES in headers
        #: The only header, if there is one (one ``bytes.find``, no cache).
        self._single = headers[0] if len(headers) == 1 else None
        #: The buffer the cache and marks below are about (``None``: none yet).
        self._buf: bytes | None = None
        #: Per header: (searched from, found at or -1) in ``_buf``.
        self._cache = [_UNSEARCHED] * len(headers)
        self._marks: bytes | bytearray | None = None
        self._misses = 0
        self._ones = (0, 0)

    @property
    def ff_rule(self) -> int:
        """What an ``FF AA`` header must keep to be a candidate."""
        return self._ff_rule

    @ff_rule.setter
    def ff_rule(self, rule: int) -> None:
        if rule != self._ff_rule:
            self._ff_rule = rule
            self._buf = None  # what was found in the buffer was found by the old rule
            self._program = _compile(self.headers, rule, self._quad, self._project)

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
        checks = self._program.checks
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
            b0 = buf[p]
            if b0 == 0xAA or b0 == 0x55:  # ``la_fits``, inline: the hot path of every frame
                if p + 4 >= len(buf) or buf[p + 2] <= LA_MAX_LEN[buf[p + 4]]:
                    return p
            elif checks[b0](buf, p):
                return p
            self._misses += 1
            if self._misses >= DENSE_AFTER:
                marks = self._marks = self._all_marks(buf)
                return marks.find(1, p + 1)
            pos = p + 1

    def passes(self, buf: bytes, p: int) -> bool:
        """Does the header at ``p`` (one of ``headers``) keep its rule?"""
        return self._program.checks[buf[p]](buf, p)

    def marks(self, buf: bytes) -> bytes | bytearray:
        """One byte per byte of ``buf``: 1 where an LA or ``FF AA`` candidate starts, else 0.

        From the anchors when they are sparse enough, else in C throughout (see the
        module docstring); the two agree byte for byte.
        """
        table = self._program.anchors
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
        ``_anchor_table``): each is checked with the conjunctions it anchors.

        ``None`` once more than ``most`` anchors have come (``marks_in_c`` is cheaper
        then): the work spent is bounded by ``most`` checks.
        """
        n = len(buf)
        budget = n if most is None else most
        marks = bytearray(n)
        program = self._program
        by_anchor = program.by_anchor
        find = anchors.find
        q = find(1)
        while q >= 0:
            budget -= 1
            if budget < 0:
                return None
            for header, offset, conj in by_anchor[buf[q]]:
                p = q - offset
                if p >= 0 and buf.startswith(header, p) and fits(conj, buf, p):
                    marks[p] = 1
            q = find(1, q + 1)
        # Headers whose farthest anchor has not arrived yet: their rule with what is in.
        for header, rule, due in program.tails:
            p = buf.find(header, n - due if n > due else 0)
            while p >= 0:
                if fits(rule, buf, p):
                    marks[p] = 1
                p = buf.find(header, p + 1)
        return marks

    def marks_in_c(self, buf: bytes) -> bytes:
        """``marks``, in C throughout: each byte's flags (a translation table per group of
        eight) become one integer, in which a shift by ``8 * offset + bit`` brings the flag
        of byte ``p + offset`` to bit 0 of byte ``p``; a rule is ORs of ANDs of such shifts.
        (Only bit 0 of each byte is kept: the other bits of a result byte mean nothing.)
        """
        n = len(buf)
        program = self._program
        flags = [int.from_bytes(buf.translate(t) + pad, "little") for t, pad in program.groups]
        found = 0
        for head, conjs in program.marked:
            at = -1
            for g, shift in head:
                at &= flags[g] >> shift
            if not at:
                continue
            for conj in conjs:
                m = at
                for g, shift in conj:
                    m &= flags[g] >> shift
                found |= m
        if self._ones[0] != n:
            self._ones = (n, int.from_bytes(b"\x01" * n, "little"))
        return (found & self._ones[1]).to_bytes(n, "little")

    def _anchor_table(self) -> bytes | None:
        """Translation table: 1 for a byte that may anchor a candidate, else 0; ``None``
        when some header has no anchor (``FF AA`` under ``FF_ANY``)."""
        return self._program.anchors

    def _all_marks(self, buf: bytes) -> bytes | bytearray:
        """``marks``, plus every ``EE DD`` when it is one of the headers."""
        marks = self.marks(buf)
        if self._ee_dd:
            q = buf.find(PROJECT_FINISHED_BYTES)
            if q >= 0:
                marks = bytearray(marks)
                while q >= 0:
                    marks[q] = 1
                    q = buf.find(PROJECT_FINISHED_BYTES, q + 1)
        return marks
