"""What lies at a position of the byte stream: the reassembler's frame-by-frame verdicts.

``protocol/reassembler.py`` walks the stream; at each candidate header it asks
:class:`FrameJudge` what is there (``parse_at``): a complete frame (or ``EE DD``), a frame
still lacking bytes, a hold, or an invalid candidate with the reason it is one.  Every
rule it applies is the rulebook's (``protocol/rulebook.py``: headers, lengths, checksums,
what a frame may be); what it adds is how the families share one stream:

* Stepper requests: on a stream that may carry both steppers (a simulator of a mixed bus,
  ``motorbus decode``), both checksums decide: with 11 bytes at hand the 11-byte frame is
  taken if its checksum holds, else the 9-byte frame if its checksum holds.  The 11-byte
  frame can never end in the ``FF AA`` of a next frame while the 9-byte checksum holds: a
  valid 9-byte frame sums to twice its checksum (even), and ``FF AA`` at bytes 9..10 would
  need it to sum to ``AA - FF = AB`` (odd).  Limit: with only 9 or 10 bytes at hand and
  the 9-byte checksum holding, the 9-byte frame is taken at once (a device must not wait
  for bytes that never come), so an 11-byte request whose byte 2 is also a quad address
  and whose byte 8 equals the sum of bytes 0..7 (1 in 256) is cut short if the stream
  pauses right after its byte 8 or 9.
* Stepper replies carry neither length nor checksum (A0-04, A1-09): only the caller knows
  what it asked, so it says which reply shapes are acceptable (``Reassembler.expect``);
  ``expect([])`` means none is, and ``FF AA`` bytes are then discarded as "unexpected
  reply shape".  Without an expectation any 6-byte reply that keeps the rulebook's reply
  rule is taken, and ``FF AA 3E P 00 00`` starts a 226-byte dump.
* Checksummed frames win over checksum-less ones: a 6-byte reply (or a request, whose
  checksum may hold by accident) at ``p`` is refused ("overlaps an LA frame", one byte) if
  a complete, checksum-valid LA frame starts at ``p + 1 .. p + size - 1``.  If such an LA
  frame is still incomplete, the stream waits for it, unless a later valid frame already
  proves its header garbage, or the stream has ended.  (An LA header whose first byte is
  the candidate's last byte is not waited for: a request's checksum byte is ``55`` once
  in 256.)
* A dump is consumed whole: once its header has matched, the reassembler waits for all
  226 bytes, and ``EE DD``, ``AA 55`` or ``FF AA`` inside it are data.  On a stream that
  may carry requests as well a request whose checksum holds is taken first (the 0x3E
  request starts with the dump header), so a dump whose first 11 (or 9) bytes satisfy a
  request checksum, 1 in 256 (or 2), is cut there.  A host (``REPLY``) stream never is.

``later_valid_frame`` finds the first complete checksum-valid frame after a position
(which proves an incomplete header before it garbage), from answers kept across reads in
a ``valid_index.ValidIndex``; ``unexpected_run`` says how many bytes a refused stepper
reply costs.  ``finder`` (a ``candidates.CandidateFinder``) says where a frame may start,
by the same rules.  Sans-I/O, pure: positions in ``buf`` are relative to the bytes being
scanned, whose stream offset is ``base``.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable

from motorbus.protocol.base import (
    FF_AA,
    LA_REPLY_HEADER,
    LA_REQUEST_HEADER,
    PROJECT_FINISHED_BYTES,
    Direction,
    Family,
    FrameShape,
    ProjectFinishedMarker,
)
from motorbus.protocol.candidates import CandidateFinder
from motorbus.protocol.frames import Frame, Item
from motorbus.protocol.rulebook import (
    DUMP_SHAPE,
    FF_ANY,
    FF_REPLY,
    FF_REQUEST,
    FF_REQUEST_ONLY,
    LA_MAX_LEN,
    LA_MIN_LEN,
    PROJECT_REQUEST_MAY,
    PROJECT_REQUEST_SIZE,
    QUAD_REQUEST_MAY,
    QUAD_REQUEST_SIZE,
    STEPPER_REPLY_SHAPE,
    STEPPER_REPLY_SIZE,
    fits,
    la_claim,
    la_sum_ok,
    request_sum_ok,
)
from motorbus.protocol.valid_index import ValidIndex

__all__ = [
    "COMPLETE",
    "HEADER_FIRST_BYTES",
    "INCOMPLETE",
    "INVALID",
    "REASONS",
    "UNEXPECTED",
    "WAIT",
    "FrameJudge",
    "discard_reason",
]

_QUAD_ONLY_ADDRESSES = frozenset((0x09, 0xBC))  # "all motors" and "save" (doc 001 B.2)
#: First bytes of every header: a buffer ending in one may be cut mid-header.
HEADER_FIRST_BYTES = frozenset((0x55, 0xAA, 0xFF, 0xEE))

# Outcome of trying to parse a frame at a position.
COMPLETE = 0
#: The frame at this position lacks bytes of its own; a later valid frame may prove it garbage.
INCOMPLETE = 1
INVALID = 2
#: Hold the stream here until more bytes come, with no skipping ahead: a dump whose header
#: matched, or a checksum-less candidate with an unfinished LA frame starting inside it.
WAIT = 3

# Why an ``INVALID`` candidate is refused (the size slot of its verdict).
_BAD_LENGTH = 1
_BAD_CHECKSUM = 2
UNEXPECTED = 3
_OVERLAP = 4
_BAD_COMMAND = 5
#: The discard reason, by the code of an ``INVALID`` verdict.
REASONS = {
    _BAD_LENGTH: "bad length",
    _BAD_CHECKSUM: "bad checksum",
    UNEXPECTED: "unexpected reply shape",
    _OVERLAP: "overlaps an LA frame",
    _BAD_COMMAND: "unknown command",
}


def discard_reason(code: int) -> str:
    """The discard reason for the code of an ``INVALID`` verdict."""
    return REASONS.get(code, "invalid")


#: Builds a ``Frame`` without its Python-level ``__new__`` (one per frame, the hot path).
_new = tuple.__new__
#: The shortest self-validating frame: an LA frame of Len 2.
_SHORTEST_VALID = LA_MIN_LEN + 5

# Verdicts of ``_la_inside``.
_CLEAR = 0
_REFUSE = 1
_HOLD = 2


class FrameJudge:
    """Verdicts on candidate frames for one stream's direction and families.

    Args:
        direction: ``REPLY``, ``REQUEST`` or ``None`` for both, as for the reassembler.
        families: the device families that may appear on the stream.

    Attributes the reassembler sets: ``expected`` (the acceptable stepper reply shapes,
    ``None`` for the default), ``base`` (the stream offset of ``buf[0]`` in the bytes
    being scanned) and ``index`` (a fresh ``ValidIndex`` when the stream ends).
    ``finder`` finds the candidate headers, for the reassembler and for the index.
    """

    def __init__(self, direction: Direction | None, families: Iterable[Family]) -> None:
        families = frozenset(families)
        self.direction = direction
        self._expected: tuple[FrameShape, ...] | None = None
        self.base = 0
        self.index = ValidIndex()
        la = Family.LA in families
        project = Family.PROJECT_STEPPER in families
        quad = Family.QUAD_STEPPER in families
        headers: list[bytes] = []
        la_headers: list[bytes] = []
        if la and direction in (Direction.REPLY, None):
            la_headers.append(LA_REPLY_HEADER)
        if la and direction in (Direction.REQUEST, None):
            la_headers.append(LA_REQUEST_HEADER)
        headers += la_headers
        if project or quad:
            headers.append(FF_AA)
        if project and direction in (Direction.REPLY, None):
            headers.append(PROJECT_FINISHED_BYTES)
        #: Every header this stream may carry, in the order the scanner searches them.
        self.headers = tuple(headers)
        #: LA headers this stream may carry: a stepper candidate that one of them starts
        #: inside of is checked against it (checksummed frames win).
        self._la_headers = tuple(la_headers)
        #: Headers of self-validating frames (the only ones that prove a header garbage).
        valid_headers = list(la_headers)
        if (project or quad) and direction is not Direction.REPLY:
            valid_headers.append(FF_AA)
        self._valid_headers = tuple(valid_headers)
        self._project = project
        self._quad = quad
        #: The reply shapes without an expectation, in order of preference.
        self._default_shapes = (
            (DUMP_SHAPE, STEPPER_REPLY_SHAPE) if project else (STEPPER_REPLY_SHAPE,)
        )
        self.finder = CandidateFinder(self.headers, self._ff_rule(), quad=quad, project=project)

    @property
    def expected(self) -> tuple[FrameShape, ...] | None:
        """The acceptable stepper reply shapes (``None``: the default ones)."""
        return self._expected

    @expected.setter
    def expected(self, shapes: tuple[FrameShape, ...] | None) -> None:
        self._expected = shapes
        self.finder.ff_rule = self._ff_rule()

    def _ff_rule(self) -> int:
        """What an ``FF AA`` header must show to be a candidate (``protocol/candidates.py``)."""
        if self.direction is Direction.REQUEST:
            return FF_REQUEST_ONLY
        if self._expected is not None:
            return FF_ANY  # the shapes decide, and a refusal has its reason
        # The default reply rule is the request rule without its 0x8E exception.
        return FF_REPLY if self.direction is Direction.REPLY else FF_REQUEST

    def parse_at(self, buf: bytes, p: int, final: bool) -> tuple[int, int, Item | None]:
        """Try to parse one item at ``p``: (state, size or reason code, item)."""
        b0 = buf[p]
        if b0 == 0xAA:  # AA 55: LA reply
            return self._parse_la(buf, p, Direction.REPLY)
        if b0 == 0x55:  # 55 AA: LA request
            return self._parse_la(buf, p, Direction.REQUEST)
        if b0 == 0xEE:  # EE DD between frames
            return COMPLETE, 2, ProjectFinishedMarker()
        return self._parse_stepper(buf, p, final)

    def _parse_la(self, buf: bytes, p: int, direction: Direction) -> tuple[int, int, Item | None]:
        avail = len(buf) - p
        if avail < 3:
            return INCOMPLETE, 0, None
        length = buf[p + 2]
        if length < LA_MIN_LEN:
            return INVALID, _BAD_LENGTH, None
        if avail >= 5 and length > LA_MAX_LEN[buf[p + 4]]:  # ``rulebook.la_fits``, inline
            return INVALID, _BAD_COMMAND, None
        total = length + 5
        if avail < total:
            return INCOMPLETE, 0, None
        end = p + total
        if not la_sum_ok(buf, p, end):
            return INVALID, _BAD_CHECKSUM, None
        return COMPLETE, total, _new(Frame, (Family.LA, direction, buf[p:end]))

    def _parse_stepper(self, buf: bytes, p: int, final: bool) -> tuple[int, int, Item | None]:
        avail = len(buf) - p
        if self.direction is not Direction.REPLY:
            state, size, item = self._parse_stepper_request(buf, p, avail, final)
            if state != INVALID or self.direction is Direction.REQUEST:
                return state, size, item
        return self._parse_stepper_reply(buf, p, avail, final)

    def _parse_stepper_request(
        self, buf: bytes, p: int, avail: int, final: bool
    ) -> tuple[int, int, Item | None]:
        """A checksummed ``FF AA`` request: 9 bytes (quad) or 11 (project).

        With both families possible, the two checksums decide (see the module
        docstring); a candidate is refused if a checksum-valid LA frame starts inside it,
        or if it may be neither a quad request nor a project one
        (``rulebook.QUAD_REQUEST_MAY``, ``rulebook.PROJECT_REQUEST_MAY``).
        """
        quad = self._quad and fits(QUAD_REQUEST_MAY, buf, p)
        project = self._project and fits(PROJECT_REQUEST_MAY, buf, p)
        if not (quad or project):
            return INVALID, _BAD_COMMAND, None
        quad_ok = quad and avail >= QUAD_REQUEST_SIZE and request_sum_ok(buf, p, QUAD_REQUEST_SIZE)
        candidates: list[tuple[int, Family]] = []
        waiting = False
        if project:
            if avail < PROJECT_REQUEST_SIZE:
                waiting = not quad_ok  # a valid 9-byte frame is taken rather than waited on
            elif request_sum_ok(buf, p, PROJECT_REQUEST_SIZE):
                # If the 9-byte checksum holds too, the 11-byte frame is preferred; it
                # cannot end in the ``FF AA`` of a next frame (see the module docstring).
                candidates.append((PROJECT_REQUEST_SIZE, Family.PROJECT_STEPPER))
        if quad_ok:
            candidates.append((QUAD_REQUEST_SIZE, Family.QUAD_STEPPER))
        elif quad and avail < QUAD_REQUEST_SIZE:
            waiting = True
        refused = False
        for size, family in candidates:
            verdict = self._la_inside(buf, p, size, final)
            if verdict == _CLEAR:
                return COMPLETE, size, _new(Frame, (family, Direction.REQUEST, buf[p : p + size]))
            if verdict == _HOLD:
                return WAIT, 0, None
            refused = True
        if waiting and not final and not refused:
            return INCOMPLETE, 0, None
        return INVALID, _OVERLAP if refused else _BAD_CHECKSUM, None

    def _parse_stepper_reply(
        self, buf: bytes, p: int, avail: int, final: bool
    ) -> tuple[int, int, Item | None]:
        shapes = self._expected
        if shapes is None:
            shapes = self._default_shapes
        refused = False
        for shape in shapes:  # in order of preference: the first fitting shape wins
            if not shape.matches_at(buf, p, avail):
                continue
            size = shape.length
            if avail < len(shape.pattern) or avail < size:
                if size > STEPPER_REPLY_SIZE and avail >= len(shape.pattern) and not final:
                    # A dump whose header matched is consumed whole: its data may hold
                    # anything (AA 55, FF AA, EE DD), so nothing inside may cut it short.
                    return WAIT, 0, None
                return INCOMPLETE, 0, None  # fits so far: wait for the rest
            if size <= STEPPER_REPLY_SIZE:
                verdict = self._la_inside(buf, p, size, final)
                if verdict == _REFUSE:
                    refused = True
                    continue
                if verdict == _HOLD:
                    return WAIT, 0, None
            raw = buf[p : p + size]
            return COMPLETE, size, _new(Frame, (self._stepper_family(raw), Direction.REPLY, raw))
        if refused:
            return INVALID, _OVERLAP, None
        # The refused reply may still be arriving: wait for its bytes (or a header), so
        # that a reply split across reads is discarded as one run, as a whole one is.
        still_arriving = avail < STEPPER_REPLY_SIZE and not final
        if still_arriving and self.unexpected_run(buf, p) >= p + avail - 1:
            return INCOMPLETE, 0, None
        return INVALID, UNEXPECTED, None

    def _la_inside(self, buf: bytes, p: int, size: int, final: bool) -> int:
        """Does a checksummed LA frame start inside the candidate ``buf[p : p + size]``?

        ``_REFUSE`` if a complete, checksum-valid one starts at ``p + 1 .. p + size - 1``
        (checksummed frames win); ``_HOLD`` if one may still (its header is there but
        its bytes are not, and no later valid frame proves that header garbage);
        ``_CLEAR`` otherwise.  At the end of the stream nothing is held.
        """
        headers = self._la_headers
        if not headers:
            return _CLEAR
        last = p + size - 1  # the last byte at which an inner frame may start
        if buf.find(0x55, p + 1, last + 2) < 0:
            return _CLEAR  # both LA headers hold a 0x55: one search rules them out
        hold = False
        for header in headers:
            q = buf.find(header, p + 1, last + 2)
            while q >= 0:
                direction = Direction.REPLY if header == LA_REPLY_HEADER else Direction.REQUEST
                state, _, _ = self._parse_la(buf, q, direction)
                if state == COMPLETE:
                    return _REFUSE
                if state == INCOMPLETE and not final and not hold:
                    hold = self.later_valid_frame(buf, q + 1) < 0
                q = buf.find(header, q + 1, last + 2)
        # A candidate whose last byte is the first half of an LA header is not held for
        # the next byte: a request's checksum byte is 0x55 once in 256, and a simulator
        # holding that request would stall the bus until the host timed out.
        return _HOLD if hold else _CLEAR

    def unexpected_run(self, buf: bytes, p: int) -> int:
        """End of the refused stepper reply at ``p``: up to 6 bytes, or the next header."""
        n = len(buf)
        end = p + 1
        limit = min(p + STEPPER_REPLY_SIZE, n)
        while end < limit:
            if end == n - 1 and buf[end] in HEADER_FIRST_BYTES:
                break
            if any(buf.startswith(h, end) for h in self.headers):
                break
            end += 1
        return end

    def _stepper_family(self, raw: bytes) -> Family:
        if self._project:
            if not self._quad:
                return Family.PROJECT_STEPPER
            # Both possible (motorbus decode without --family): the only telling bytes
            # are the address values each controller alone uses (A0-05).
            b2 = raw[2]
            if b2 not in _QUAD_ONLY_ADDRESSES and (b2 or raw[3] != 0x09):
                return Family.PROJECT_STEPPER
        return Family.QUAD_STEPPER

    def later_valid_frame(self, buf: bytes, start: int) -> int:
        """Position of the first complete checksum-valid frame at or after ``start``, or -1.

        Only self-validating frames count (LA frames, stepper requests): a stepper
        reply has no checksum, so finding one proves nothing.  The answer comes from
        an index kept across ``feed`` calls (``ValidIndex``): each candidate header is
        judged when first seen and again only when bytes it depends on arrive, so a
        stream of look-alike headers costs bounded work per byte however it is read.
        """
        n = len(buf)
        if n - start < _SHORTEST_VALID:
            return -1  # no self-validating frame fits in what is left
        ix = self.index
        base = self.base
        n_abs = base + n
        s = base + start
        if s > ix.to:
            ix.restart(s)
        elif s < ix.lo:
            # Positions before the index (a query from inside an earlier candidate).
            self._index_range(buf, s, ix.lo)
            ix.lo = s
        valid = ix.valid
        if valid and valid[0] < base:
            ix.prune(base)
        due = ix.due
        while due and due[0][0] <= n_abs:
            _, q = heapq.heappop(due)
            if q >= base:
                self._judge(buf, q)
            else:
                ix.forget(q)
        if valid:
            found = ix.first_valid(s)
            if found >= 0:
                return found - base
        if ix.to >= n_abs - 1:
            return -1  # every place a header can start is judged: none is valid
        return self._extend_index(buf, s)

    def _extend_index(self, buf: bytes, s: int) -> int:
        """Index candidates from ``ix.to`` on until one is valid at or after ``s``.

        Candidates come from the finder: a header it skips cannot be valid, as its
        command bytes are in and wrong (it keeps a header whose bytes are still due).
        """
        ix = self.index
        base = self.base
        last = base + len(buf) - 1  # a header needs two bytes: none can start here yet
        find = self.finder.find
        valid_headers = self._valid_headers
        while True:
            since = max(ix.to, base)
            q = find(buf, since - base) if since < last else -1
            if q < 0:
                ix.to = max(ix.to, last)
                return -1
            ix.to = q + base + 1
            if buf[q : q + 2] in valid_headers and self._judge(buf, q + base) and q + base >= s:
                return q

    def _index_range(self, buf: bytes, lo: int, hi: int) -> None:
        """Judge every candidate header at stream offsets ``lo <= q < hi``."""
        base = self.base
        find = self.finder.find
        valid_headers = self._valid_headers
        q = find(buf, lo - base)
        while 0 <= q < hi - base:
            if buf[q : q + 2] in valid_headers:
                self._judge(buf, q + base)
            q = find(buf, q + 1)

    def _judge(self, buf: bytes, q_abs: int) -> bool:
        """Is the candidate at stream offset ``q_abs`` a complete valid frame now?

        Records the answer in the index, and when later bytes may change it.
        """
        p = q_abs - self.base
        n = len(buf)
        avail = n - p
        if buf[p] == 0xFF:
            state, code, _ = self._parse_stepper_request(buf, p, avail, True)
            never = state == INVALID and code == _BAD_COMMAND  # no request, whatever follows
            due = -1 if never else self._request_due(buf, p, avail)
            valid = state == COMPLETE
        else:
            total = la_claim(buf, p)
            if 0 < total <= avail:
                valid, due = la_sum_ok(buf, p, p + total), -1
            else:
                valid, due = False, p + 3 if total == 0 else p + total if total > 0 else -1
        self.index.record(q_abs, valid, due + self.base if due >= 0 else -1)
        return valid

    def _request_due(self, buf: bytes, p: int, avail: int) -> int:
        """Where the verdict on a candidate that may be a request (at ``p``) may next change,
        or -1 if never.

        Before the shortest request is in, nothing is decided: when it is.  Then, until
        the widest window (11 bytes and the header that may start at its last byte) is
        in: at the next byte.  Then: when an LA frame starting inside it is complete.
        """
        shortest = QUAD_REQUEST_SIZE if self._quad else PROJECT_REQUEST_SIZE
        if avail < shortest:
            return p + shortest
        window = PROJECT_REQUEST_SIZE + 1
        if avail < window:
            return p + avail + 1
        due = -1
        n = p + avail
        for header in self._la_headers:
            q = buf.find(header, p + 1, p + window)
            while q >= 0:
                total = la_claim(buf, q)
                d = q + 3 if total == 0 else q + total if n - q < total else -1
                if d >= 0 and (due < 0 or d < due):
                    due = d
                q = buf.find(header, q + 1, p + window)
        return due
