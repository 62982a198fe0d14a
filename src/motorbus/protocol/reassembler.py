"""Cut frames out of a serial byte stream, resynchronising after any garbage.

Sans-I/O: ``feed(bytes)`` returns what the bytes completed - frames, the project
stepper's ``EE DD`` event, and runs of discarded bytes - and keeps the rest for the
next call.  No clock, no asyncio; it never raises on any input.

How each family is framed
-------------------------
* LA frames (``55 AA`` requests, ``AA 55`` replies) carry their length
  (``Len = total - 5``, docs/protocols.md A2-01) and a checksum, so they are validated on
  their own.  A header whose length or checksum is wrong costs one byte: the search
  for the next header starts at the following byte.
* Stepper requests (``FF AA``, 11 bytes for the project stepper, 9 for the quad
  stepper) carry a checksum (the 8-bit sum of every byte before it) and are
  validated the same way.  On a stream that may carry both (a simulator of a mixed
  bus, ``motorbus decode``), both checksums decide: with 11 bytes at hand the
  11-byte frame is taken if its checksum holds (whether or not the 9-byte one holds
  too), else the 9-byte frame if its checksum holds.  The 11-byte frame can never
  end in the ``FF AA`` of a next frame while the 9-byte checksum holds: a valid
  9-byte frame sums to twice its checksum (an even number), and ``FF AA`` at bytes
  9..10 would need it to sum to ``AA - FF = AB`` (odd).  Limit: with only 9 or 10
  bytes at hand and the 9-byte checksum holding, the 9-byte frame is taken at once
  (a device must not wait for bytes that never come), so an 11-byte request whose
  byte 8 happens to equal the sum of bytes 0..7 (1 in 256) is cut short if the
  stream pauses right after its byte 8 or 9.
* Stepper replies (``FF AA`` + 4 bytes, or the 226-byte project dump) carry neither
  length nor checksum (A0-04, A1-09).  Only the caller knows what it asked, so it
  tells the reassembler which reply shapes are acceptable right now with
  :meth:`Reassembler.expect`; ``expect([])`` means none is, and ``FF AA`` bytes are
  then discarded as "unexpected reply shape".  Without an expectation
  (``expect(None)``, the default) any 6-byte ``FF AA`` frame is taken, and
  ``FF AA 3E P 00 00`` starts a 226-byte dump.
* Checksummed frames win over checksum-less ones.  A 6-byte stepper reply (or a
  stepper request, whose checksum may hold by accident) at ``p`` is refused
  ("overlaps an LA frame", one byte) if a complete, checksum-valid LA frame starts
  at ``p + 1 .. p + size - 1``: a stray ``FF`` before an ``AA 55`` status costs that
  byte, not the status.  If such an LA frame is still incomplete, the stream waits
  for it, unless a later valid frame already proves its header garbage, or the
  stream has ended; an LA frame that turns out invalid leaves the stepper frame
  to be taken.  (An LA header whose first byte is the candidate's last byte is not
  waited for: a request's checksum byte is ``55`` once in 256.)
* A dump is consumed whole: once an acceptable dump header ``FF AA 3E P 00 00`` has
  matched, the reassembler waits for all 226 bytes, and ``EE DD``, ``AA 55`` or
  ``FF AA`` inside it are data.  On a stream that may carry requests as well
  (``motorbus decode --direction any``, the default) a request whose checksum holds is
  taken first, since the 0x3E request itself starts with the dump header; so a dump
  whose first 11 (or, with the quad stepper possible, 9) bytes happen to satisfy a
  request checksum, 1 dump in 256 (or 2), is cut there.  A host (``REPLY``) stream
  never is.
* ``EE DD`` (project finished, A0-06) is recognised only where a frame may start,
  never inside a frame.

A header that claims more bytes than have arrived waits for them - unless a later,
complete, checksum-valid frame is already in the buffer, which proves the header was
garbage; the reassembler then skips to that frame instead of stalling behind it.

Work per input byte is bounded whatever the junk and however the stream is read: the
search for that later frame is kept across ``feed`` calls (``valid_index.ValidIndex``:
each candidate header is judged when first seen and again only when bytes its verdict
depends on arrive), checksums are summed in C, and a run of discarded bytes is joined
once.  ``tests/protocol/test_reassembler_work.py`` counts the calls per byte.

Accounting: the items ``feed`` returns cover the bytes it consumed contiguously and
in order (``ProjectFinishedMarker.raw`` is ``EE DD``), so the stream offset of an item is
the sum of ``len(raw)`` of the items before it; every byte fed is in a frame, an
event, a discarded run, or the buffer.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

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
from motorbus.protocol.valid_index import ValidIndex, sum8_at

__all__ = [
    "LA_MAX_FRAME",
    "MAX_BUFFER",
    "Discarded",
    "Frame",
    "Item",
    "ProjectFinishedMarker",
    "Reassembler",
    "ReassemblerStats",
]

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
#: Bound on the bytes kept between two ``feed`` calls.  What is kept is at most one
#: incomplete frame (the longest being an LA frame of 260 bytes), so 1 KiB is ample;
#: anything beyond it is discarded as overflow and counted.
MAX_BUFFER = 1024

_PROJECT_OPCODES = frozenset(range(0x1E, 0xAF, 0x10))  # 1E, 2E, ... AE (doc 000 A.4)
_QUAD_ONLY_ADDRESSES = frozenset((0x09, 0xBC))  # "all motors" and "save" (doc 001 B.2)
_DUMP_SHAPE = FrameShape.exact(PROJECT_DUMP_SIZE, 0xFF, 0xAA, 0x3E, frozenset(range(1, 5)), 0, 0)
_ANY_STEPPER_REPLY = FrameShape.exact(STEPPER_REPLY_SIZE, 0xFF, 0xAA)
_HEADER_FIRST_BYTES = frozenset((0x55, 0xAA, 0xFF, 0xEE))


class Frame(NamedTuple):
    """A complete frame cut from the stream.

    A NamedTuple rather than a dataclass: it is immutable all the same, and the
    reassembler builds one per frame on the hot path, where a tuple is ~3x cheaper.
    """

    family: Family
    direction: Direction
    raw: bytes


class Discarded(NamedTuple):
    """A run of bytes that belonged to no frame, and why they were dropped."""

    raw: bytes
    reason: str


Item = Frame | ProjectFinishedMarker | Discarded


@dataclass(slots=True)
class ReassemblerStats:
    """Counters; every byte fed ends up in a frame, an event, a discard, or the buffer."""

    frames: int = 0
    events: int = 0
    discarded_bytes: int = 0
    #: Number of discarded runs: times the stream had to be resynchronised.
    resyncs: int = 0
    #: Discarded bytes by reason.
    by_reason: dict[str, int] = field(default_factory=dict)


# Outcome of trying to parse a frame at a position.
_COMPLETE = 0
#: The frame at this position lacks bytes of its own; a later valid frame may prove it garbage.
_INCOMPLETE = 1
_INVALID = 2
#: Hold the stream here until more bytes come, with no skipping ahead: a dump whose header
#: matched, or a checksum-less candidate with an unfinished LA frame starting inside it.
_WAIT = 3

# Verdicts of ``_la_inside``.
_CLEAR = 0
_REFUSE = 1
_HOLD = 2


class Reassembler:
    """Turns a byte stream into frames, events and discarded runs.

    Args:
        direction: ``REPLY`` on the host side (what devices send), ``REQUEST`` in a
            simulator (what hosts send), ``None`` for both (``motorbus decode``).
        families: the device families that may appear on this stream.
        max_buffer: bound on the bytes kept between calls (see ``MAX_BUFFER``).
        stats: the counters to add to (a bus keeps one set across the reassemblers of
            its reconnects); fresh ones by default.
    """

    def __init__(
        self,
        *,
        direction: Direction | None = Direction.REPLY,
        families: Iterable[Family] = tuple(Family),
        max_buffer: int = MAX_BUFFER,
        stats: ReassemblerStats | None = None,
    ) -> None:
        self.direction = direction
        self.families = frozenset(families)
        self.max_buffer = max_buffer
        self.stats = stats if stats is not None else ReassemblerStats()
        self._buf = b""
        #: Stream offset of ``self._buf[0]`` (bytes consumed so far), and of ``buf[0]`` in
        #: the buffer being scanned.
        self._buf_abs = 0
        self._base = 0
        self._expected: tuple[FrameShape, ...] | None = None
        # The open discarded run of a ``feed`` call: (out, index in out, parts, reason), so that a
        # run of single-byte discards is joined once instead of copied at every byte.
        self._run: tuple[list[Item], int, list[bytes], str] | None = None
        self._index = ValidIndex()
        la = Family.LA in self.families
        project = Family.PROJECT_STEPPER in self.families
        quad = Family.QUAD_STEPPER in self.families
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
        self._headers = tuple(headers)
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
        # The hot path (one family, one header) gets a single bytes.find per frame.
        self._only_header = headers[0] if len(headers) == 1 else None

    # -- public API -------------------------------------------------------------

    def expect(self, shapes: Sequence[FrameShape] | None) -> None:
        """Say which stepper reply shapes are acceptable from now on.

        ``None`` restores the default (any 6-byte ``FF AA`` reply, or a 226-byte dump
        after ``FF AA 3E P 00 00``); an empty list means no stepper reply is acceptable
        (``FF AA`` bytes are discarded as "unexpected reply shape"; LA frames, stepper
        requests and ``EE DD`` still pass).  The bus calls this before writing a stepper
        request, listing the reply it awaits and any unsolicited "done" replies it
        still accepts.  Bytes already buffered are re-examined by the next ``feed``
        (``feed(b"")`` re-examines them at once).
        """
        self._expected = tuple(shapes) if shapes is not None else None

    @property
    def buffered(self) -> int:
        """Bytes held back, waiting to complete a frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Item]:
        """Add ``data`` to the stream; return every item it completed, in order."""
        buf = self._buf + data if self._buf else bytes(data)
        out: list[Item] = []
        self._base = self._buf_abs
        pos = self._scan(buf, 0, out, final=False)
        rest = buf[pos:]
        if len(rest) > self.max_buffer:
            cut = len(rest) - self.max_buffer
            self._discard(out, rest[:cut], "overflow")
            rest = rest[cut:]
            pos += cut
        self._buf = rest
        self._buf_abs += pos
        if self._run is not None:
            self._close_run()
        return out

    def end_of_stream(self) -> list[Item]:
        """No more bytes will come: resolve what is buffered (for finite inputs)."""
        buf, self._buf = self._buf, b""
        out: list[Item] = []
        self._base = self._buf_abs
        pos = self._scan(buf, 0, out, final=True)
        if pos < len(buf):
            self._discard(out, buf[pos:], "truncated frame")
        self._buf_abs += len(buf)
        self._index = ValidIndex()
        self._close_run()
        return out

    # -- the scanner -------------------------------------------------------------

    def _scan(self, buf: bytes, pos: int, out: list[Item], *, final: bool) -> int:
        """Parse ``buf`` from ``pos``; append items to ``out``; return where to resume."""
        n = len(buf)
        only = self._only_header
        # Next known position of each header (-2 = not searched yet), so that a
        # stream with several possible headers costs one find per frame, not four.
        cached = [-2] * len(self._headers)
        while pos < n:
            if only is not None:
                if only in (LA_REPLY_HEADER, LA_REQUEST_HEADER):
                    pos = self._scan_la_only(buf, pos, out)
                    if pos >= n or buf.find(only, pos) < 0:
                        break
                p = buf.find(only, pos)
            else:
                p = self._next_header_cached(buf, pos, cached)
            if p < 0:
                break
            if p > pos:
                self._discard(out, buf[pos:p], "garbage")
            state, size, item = self._parse_at(buf, p, final)
            if state == _COMPLETE:
                assert item is not None
                out.append(item)
                if type(item) is Frame:
                    self.stats.frames += 1
                else:
                    self.stats.events += 1
                pos = p + size
            elif state == _INCOMPLETE:
                later = self._later_valid_frame(buf, p + 1)
                if later < 0:
                    return p
                self._discard(out, buf[p:later], "header without its frame")
                pos = later
            elif state == _WAIT:
                return p
            else:
                end = self._unexpected_run(buf, p) if size == _UNEXPECTED else p + 1
                self._discard(out, buf[p:end], _reason(size))
                pos = end
        if pos >= n:
            return n
        # No header in buf[pos:]: keep a last byte that may be the first half of one.
        keep = n - 1 if buf[n - 1] in _HEADER_FIRST_BYTES and not final else n
        if keep > pos:
            self._discard(out, buf[pos:keep], "garbage")
        return keep

    def _scan_la_only(self, buf: bytes, pos: int, out: list[Item]) -> int:
        """Fast path for a stream of LA frames only: one find and one sum per frame.

        Returns at the first position it does not settle by itself (garbage, a bad
        frame, an incomplete tail); the general loop takes over from there.
        """
        header = self._only_header
        assert header is not None
        direction = Direction.REPLY if header == LA_REPLY_HEADER else Direction.REQUEST
        first, second = header
        la = Family.LA
        new = tuple.__new__
        append = out.append
        n = len(buf)
        count = 0
        while pos + 3 <= n and buf[pos] == first and buf[pos + 1] == second:
            length = buf[pos + 2]
            end = pos + length + 5
            if end > n or length < LA_MIN_LEN:
                break
            frame = buf[pos:end]
            check = frame[-1]
            # The checksum covers Len..last data byte: the frame's sum minus the two
            # header bytes (0x55 + 0xAA = 0xFF either way round) minus the checksum.
            if (sum(frame) - 0xFF - check) & 0xFF != check:
                break
            append(new(Frame, (la, direction, frame)))
            count += 1
            pos = end
        self.stats.frames += count
        return pos

    def _next_header_cached(self, buf: bytes, pos: int, cached: list[int]) -> int:
        best = -1
        for i, h in enumerate(self._headers):
            p = cached[i]
            if p != -1 and p < pos:
                p = buf.find(h, pos)
                cached[i] = p
            if p >= 0 and (best < 0 or p < best):
                best = p
        return best

    def _parse_at(self, buf: bytes, p: int, final: bool) -> tuple[int, int, Item | None]:
        """Try to parse one item at ``p``: (state, size or reason code, item)."""
        b0 = buf[p]
        if b0 == 0xAA:  # AA 55: LA reply
            return self._parse_la(buf, p, Direction.REPLY)
        if b0 == 0x55:  # 55 AA: LA request
            return self._parse_la(buf, p, Direction.REQUEST)
        if b0 == 0xEE:  # EE DD between frames
            return _COMPLETE, 2, ProjectFinishedMarker()
        return self._parse_stepper(buf, p, final)

    def _parse_la(self, buf: bytes, p: int, direction: Direction) -> tuple[int, int, Item | None]:
        avail = len(buf) - p
        if avail < 3:
            return _INCOMPLETE, 0, None
        length = buf[p + 2]
        if length < LA_MIN_LEN:
            return _INVALID, _BAD_LENGTH, None
        total = length + 5
        if avail < total:
            return _INCOMPLETE, 0, None
        end = p + total
        if sum8_at(buf, p + 2, end - 1) != buf[end - 1]:
            return _INVALID, _BAD_CHECKSUM, None
        return _COMPLETE, total, Frame(Family.LA, direction, buf[p:end])

    def _parse_stepper(self, buf: bytes, p: int, final: bool) -> tuple[int, int, Item | None]:
        avail = len(buf) - p
        if self.direction is not Direction.REPLY:
            state, size, item = self._parse_stepper_request(buf, p, avail, final)
            if state != _INVALID or self.direction is Direction.REQUEST:
                return state, size, item
        return self._parse_stepper_reply(buf, p, avail, final)

    def _parse_stepper_request(
        self, buf: bytes, p: int, avail: int, final: bool
    ) -> tuple[int, int, Item | None]:
        """A checksummed ``FF AA`` request: 9 bytes (quad) or 11 (project).

        With both families possible, the two checksums decide (see the module
        docstring); a candidate is refused if a checksum-valid LA frame starts inside it.
        """
        quad_ok = (
            self._quad
            and avail >= QUAD_REQUEST_SIZE
            and sum8_at(buf, p, p + QUAD_REQUEST_SIZE - 1) == buf[p + QUAD_REQUEST_SIZE - 1]
        )
        candidates: list[tuple[int, Family]] = []
        waiting = False
        if self._project:
            end = p + PROJECT_REQUEST_SIZE
            if avail < PROJECT_REQUEST_SIZE:
                waiting = not quad_ok  # a valid 9-byte frame is taken rather than waited on
            elif sum8_at(buf, p, end - 1) == buf[end - 1]:
                # If the 9-byte checksum holds too, the 11-byte frame is preferred; it
                # cannot end in the ``FF AA`` of a next frame (see the module docstring).
                candidates.append((PROJECT_REQUEST_SIZE, Family.PROJECT_STEPPER))
        if quad_ok:
            candidates.append((QUAD_REQUEST_SIZE, Family.QUAD_STEPPER))
        elif self._quad and avail < QUAD_REQUEST_SIZE:
            waiting = True
        refused = False
        for size, family in candidates:
            verdict = self._la_inside(buf, p, size, final)
            if verdict == _CLEAR:
                return _COMPLETE, size, Frame(family, Direction.REQUEST, buf[p : p + size])
            if verdict == _HOLD:
                return _WAIT, 0, None
            refused = True
        if waiting and not final and not refused:
            return _INCOMPLETE, 0, None
        return _INVALID, _OVERLAP if refused else _BAD_CHECKSUM, None

    def _parse_stepper_reply(
        self, buf: bytes, p: int, avail: int, final: bool
    ) -> tuple[int, int, Item | None]:
        shapes = self._expected
        if shapes is None:
            shapes = (_DUMP_SHAPE, _ANY_STEPPER_REPLY) if self._project else (_ANY_STEPPER_REPLY,)
        head = buf[p : p + min(avail, 8)]
        refused = False
        for shape in shapes:  # in order of preference: the first fitting shape wins
            if not shape.matches(head):
                continue
            size = shape.length
            if avail < len(shape.pattern) or avail < size:
                if size > STEPPER_REPLY_SIZE and avail >= len(shape.pattern) and not final:
                    # A dump whose header matched is consumed whole: its data may hold
                    # anything (AA 55, FF AA, EE DD), so nothing inside may cut it short.
                    return _WAIT, 0, None
                return _INCOMPLETE, 0, None  # fits so far: wait for the rest
            if size <= STEPPER_REPLY_SIZE:
                verdict = self._la_inside(buf, p, size, final)
                if verdict == _REFUSE:
                    refused = True
                    continue
                if verdict == _HOLD:
                    return _WAIT, 0, None
            raw = buf[p : p + size]
            return _COMPLETE, size, Frame(self._stepper_family(raw), Direction.REPLY, raw)
        if refused:
            return _INVALID, _OVERLAP, None
        # The refused reply may still be arriving: wait for its bytes (or a header), so
        # that a reply split across reads is discarded as one run, as a whole one is.
        still_arriving = avail < STEPPER_REPLY_SIZE and not final
        if still_arriving and self._unexpected_run(buf, p) >= p + avail - 1:
            return _INCOMPLETE, 0, None
        return _INVALID, _UNEXPECTED, None

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
        hold = False
        for header in headers:
            q = buf.find(header, p + 1, last + 2)
            while q >= 0:
                direction = Direction.REPLY if header == LA_REPLY_HEADER else Direction.REQUEST
                state, _, _ = self._parse_la(buf, q, direction)
                if state == _COMPLETE:
                    return _REFUSE
                if state == _INCOMPLETE and not final and not hold:
                    hold = self._later_valid_frame(buf, q + 1) < 0
                q = buf.find(header, q + 1, last + 2)
        # A candidate whose last byte is the first half of an LA header is not held for
        # the next byte: a request's checksum byte is 0x55 once in 256, and a simulator
        # holding that request would stall the bus until the host timed out.
        return _HOLD if hold else _CLEAR

    def _unexpected_run(self, buf: bytes, p: int) -> int:
        """End of the refused stepper reply at ``p``: up to 6 bytes, or the next header."""
        n = len(buf)
        end = p + 1
        limit = min(p + STEPPER_REPLY_SIZE, n)
        while end < limit:
            if end == n - 1 and buf[end] in _HEADER_FIRST_BYTES:
                break
            if any(buf.startswith(h, end) for h in self._headers):
                break
            end += 1
        return end

    def _stepper_family(self, raw: bytes) -> Family:
        if not self._quad:
            return Family.PROJECT_STEPPER
        if not self._project:
            return Family.QUAD_STEPPER
        # Both possible (motorbus decode without --family): the only telling bytes
        # are the address values each controller alone uses (A0-05).
        b2, b3 = raw[2], raw[3]
        if b2 in _QUAD_ONLY_ADDRESSES or (b2 == 0 and b3 == 0x09):
            return Family.QUAD_STEPPER
        return Family.PROJECT_STEPPER

    def _later_valid_frame(self, buf: bytes, start: int) -> int:
        """Position of the first complete checksum-valid frame at or after ``start``, or -1.

        Only self-validating frames count (LA frames, stepper requests): a stepper
        reply has no checksum, so finding one proves nothing.  The answer comes from
        an index kept across ``feed`` calls (``ValidIndex``): each candidate header is
        judged when first seen and again only when bytes it depends on arrive, so a
        stream of look-alike headers costs bounded work per byte however it is read.
        """
        ix = self._index
        base = self._base
        n_abs = base + len(buf)
        s = base + start
        if s >= n_abs:
            return -1
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
        """Index candidates from ``ix.to`` on until one is valid at or after ``s``."""
        ix = self._index
        base = self._base
        n = len(buf)
        nxt = ix.next
        headers = self._valid_headers
        last = base + n - 1  # a header needs two bytes: none can start here yet
        while True:
            best = -1
            for i, header in enumerate(headers):
                q = nxt[i]
                if q < ix.to:
                    # Unknown (-1), stale (found before ``to``), or none before ``-q - 2``.
                    since = max(ix.to, -q - 2, base)
                    if since >= last:
                        continue
                    found = buf.find(header, since - base)
                    q = nxt[i] = found + base if found >= 0 else -last - 2
                    if found < 0:
                        continue
                if best < 0 or q < best:
                    best = q
            if best < 0:
                ix.to = max(ix.to, base + n - 1)
                return -1
            ix.to = best + 1
            if self._judge(buf, best) and best >= s:
                return best - base

    def _index_range(self, buf: bytes, lo: int, hi: int) -> None:
        """Judge every candidate header at stream offsets ``lo <= q < hi``."""
        base = self._base
        for header in self._valid_headers:
            q = buf.find(header, lo - base, hi - base + 1)
            while q >= 0:
                self._judge(buf, q + base)
                q = buf.find(header, q + 1, hi - base + 1)

    def _judge(self, buf: bytes, q_abs: int) -> bool:
        """Is the candidate at stream offset ``q_abs`` a complete valid frame now?

        Records the answer in the index, and when later bytes may change it.
        """
        p = q_abs - self._base
        n = len(buf)
        avail = n - p
        if buf[p] == 0xFF:
            state, _, _ = self._parse_stepper_request(buf, p, avail, True)
            due = self._request_due(buf, p, avail)
        else:
            state, _, _ = self._parse_la(buf, p, Direction.REPLY)
            if avail < 3:
                due = p + 3
            elif buf[p + 2] < LA_MIN_LEN:
                due = -1
            else:
                total = buf[p + 2] + 5
                due = p + total if avail < total else -1
        valid = state == _COMPLETE
        self._index.record(q_abs, valid, due + self._base if due >= 0 else -1)
        return valid

    def _request_due(self, buf: bytes, p: int, avail: int) -> int:
        """Where a stepper request's verdict (at ``p``) may next change, or -1 if never.

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
                if n - q < 3:
                    d = q + 3
                elif buf[q + 2] >= LA_MIN_LEN and n - q < buf[q + 2] + 5:
                    d = q + buf[q + 2] + 5
                else:
                    d = -1
                if d >= 0 and (due < 0 or d < due):
                    due = d
                q = buf.find(header, q + 1, p + window)
        return due

    def _discard(self, out: list[Item], raw: bytes, reason: str) -> None:
        stats = self.stats
        stats.discarded_bytes += len(raw)
        stats.by_reason[reason] = stats.by_reason.get(reason, 0) + len(raw)
        if out and type(out[-1]) is Discarded and out[-1].reason == reason:
            # Join the run once, when it closes: appending to it here would copy the
            # whole run at every discarded byte (quadratic in the run's length).
            run = self._run
            if run is not None and run[0] is out and run[1] == len(out) - 1:
                run[2].append(raw)
            else:
                self._close_run()
                self._run = (out, len(out) - 1, [out[-1].raw, raw], reason)
        else:
            if self._run is not None:
                self._close_run()
            stats.resyncs += 1
            out.append(Discarded(raw, reason))

    def _close_run(self) -> None:
        """Join the parts of the open discarded run into its item."""
        run = self._run
        if run is not None:
            out, index, parts, reason = run
            out[index] = Discarded(b"".join(parts), reason)
            self._run = None


_BAD_LENGTH = 1
_BAD_CHECKSUM = 2
_UNEXPECTED = 3
_OVERLAP = 4
_REASONS = {
    _BAD_LENGTH: "bad length",
    _BAD_CHECKSUM: "bad checksum",
    _UNEXPECTED: "unexpected reply shape",
    _OVERLAP: "overlaps an LA frame",
}


def _reason(code: int) -> str:
    return _REASONS.get(code, "invalid")
