"""Cut frames out of a serial byte stream, resynchronising after any garbage.

Sans-I/O: ``feed(bytes)`` returns what the bytes completed - frames, the project
stepper's ``EE DD`` event, and runs of discarded bytes - and keeps the rest for the
next call.  No clock, no asyncio; it never raises on any input.

How each family is framed
-------------------------
* LA frames (``55 AA`` requests, ``AA 55`` replies) carry their length
  (``Len = total - 5``, docs/protocols.md A2-01) and a checksum, so they are validated on
  their own.  Their CMD byte is one of the manual's nine command codes (C.3), and only a
  read or a write (01, 02) is longer than a 15-entry broadcast (Len 0x2E): a header
  followed by anything else is no frame, whatever its checksum.  A header whose length
  or checksum is wrong costs one byte: the search for the next header starts at the
  following byte.
* Stepper requests (``FF AA``, 11 bytes for the project stepper, 9 for the quad
  stepper) carry a checksum (the 8-bit sum of every byte before it) and are
  validated the same way; their byte 3 is at most 0x0F (a command, project, step or
  value), except after the 0x8E opcode (a repeat count).  A quad request's byte 2 is
  an address (motor 1..4, 09 all, 00 I/O, BC save) and a project request's byte 9 a
  step (1..10) or 00: a candidate that can be neither is no request, whatever its
  checksums.  On a stream that may carry
  both (a simulator of a mixed bus, ``motorbus decode``), both checksums decide: with
  11 bytes at hand the 11-byte frame is taken if its checksum holds (whether or not
  the 9-byte one holds too), else the 9-byte frame if its checksum holds.  The
  11-byte frame can never end in the ``FF AA`` of a next frame while the 9-byte
  checksum holds: a valid 9-byte frame sums to twice its checksum (an even number),
  and ``FF AA`` at bytes 9..10 would need it to sum to ``AA - FF = AB`` (odd).
  Limit: with only 9 or 10 bytes at hand and the 9-byte checksum holding, the 9-byte
  frame is taken at once (a device must not wait for bytes that never come), so an
  11-byte request whose byte 2 is also a quad address and whose byte 8 happens to
  equal the sum of bytes 0..7 (1 in 256) is cut short if the stream pauses right
  after its byte 8 or 9.
* Stepper replies (``FF AA`` + 4 bytes, or the 226-byte project dump) carry neither
  length nor checksum (A0-04, A1-09).  Only the caller knows what it asked, so it
  tells the reassembler which reply shapes are acceptable right now with
  :meth:`Reassembler.expect`; ``expect([])`` means none is, and ``FF AA`` bytes are
  then discarded as "unexpected reply shape".  Without an expectation
  (``expect(None)``, the default) any 6-byte ``FF AA`` frame whose byte 3 is at most
  0x0F (as in every reply of both manuals) is taken, and ``FF AA 3E P 00 00`` starts a
  226-byte dump.
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
once.  ``tests/protocol/test_reassembler_work.py`` counts the calls per byte.  And it is
small: a header whose command byte no frame carries (the rules above) is skipped in C,
as part of the garbage around it, by ``candidates.CandidateFinder``, so junk dense in
header bytes costs a few nanoseconds a byte more than junk without them, not a Python
verdict every few bytes.  Junk built to pass those rules still costs a verdict per
header (``benchmarks/bench_reassembler.py`` measures both).

Accounting: the items ``feed`` returns cover the bytes it consumed contiguously and
in order (``ProjectFinishedMarker.raw`` is ``EE DD``), so the stream offset of an item is
the sum of ``len(raw)`` of the items before it; every byte fed is in a frame, an
event, a discarded run, or the buffer.

Where it lives: this module walks the stream (the buffer between reads, the scan loop,
the discarded runs and their counters); ``protocol/frame_judge.py`` says what lies at
each candidate header, by the rules above; ``protocol/candidates.py`` finds the headers
worth a verdict; ``protocol/frames.py`` holds the items returned (``Frame``,
``Discarded``), the frame sizes and command bytes; ``protocol/valid_index.py`` the
answers kept across reads.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from itertools import repeat

from motorbus.protocol.base import (
    LA_REPLY_HEADER,
    LA_REQUEST_HEADER,
    PROJECT_FINISHED_BYTES,
    Direction,
    Family,
    FrameShape,
    ProjectFinishedMarker,
)
from motorbus.protocol.frame_judge import (
    COMPLETE,
    HEADER_FIRST_BYTES,
    INCOMPLETE,
    REASONS,
    UNEXPECTED,
    WAIT,
    FrameJudge,
)
from motorbus.protocol.frames import (
    LA_MAX_FRAME,
    LA_MAX_LEN,
    LA_MIN_LEN,
    Discarded,
    Frame,
    Item,
    ReassemblerStats,
)

# The frame sizes were defined here before frames.py; they stay importable from here.
from motorbus.protocol.frames import PROJECT_DUMP_SIZE as PROJECT_DUMP_SIZE
from motorbus.protocol.frames import PROJECT_REQUEST_SIZE as PROJECT_REQUEST_SIZE
from motorbus.protocol.frames import QUAD_REQUEST_SIZE as QUAD_REQUEST_SIZE
from motorbus.protocol.frames import STEPPER_REPLY_SIZE as STEPPER_REPLY_SIZE
from motorbus.protocol.valid_index import ValidIndex

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

#: Bound on the bytes kept between two ``feed`` calls.  What is kept is at most one
#: incomplete frame (the longest being an LA frame of 260 bytes), so 1 KiB is ample;
#: anything beyond it is discarded as overflow and counted.
MAX_BUFFER = 1024

#: Builds a NamedTuple item without its Python-level ``__new__`` (the hot path).
_new = tuple.__new__
#: A run of ``EE DD`` events.
_EVENT_RUN = re.compile(b"(?:" + re.escape(PROJECT_FINISHED_BYTES) + b")+").match


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
        #: Stream offset of ``self._buf[0]`` (bytes consumed so far).
        self._buf_abs = 0
        # The open discarded run of a ``feed`` call: (out, index in out, parts, reason), so that a
        # run of single-byte discards is joined once instead of copied at every byte.
        self._run: tuple[list[Item], int, list[bytes], str] | None = None
        #: Says what lies at each candidate header (and keeps the valid-frame index).
        self._judge = FrameJudge(direction, self.families)
        headers = self._judge.headers
        # The hot path (a stream of LA frames of one direction) takes frame after frame
        # with one sum each, without looking for headers: from a byte that may start one.
        la_only = len(headers) == 1 and headers[0] in (LA_REPLY_HEADER, LA_REQUEST_HEADER)
        self._la_first = headers[0][0] if la_only else -1
        self._la_second = headers[0][1] if la_only else -1

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
        self._judge.expected = tuple(shapes) if shapes is not None else None

    @property
    def buffered(self) -> int:
        """Bytes held back, waiting to complete a frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Item]:
        """Add ``data`` to the stream; return every item it completed, in order."""
        buf = self._buf + data if self._buf else bytes(data)
        out: list[Item] = []
        self._judge.base = self._buf_abs
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
        self._judge.base = self._buf_abs
        pos = self._scan(buf, 0, out, final=True)
        if pos < len(buf):
            self._discard(out, buf[pos:], "truncated frame")
        self._buf_abs += len(buf)
        self._judge.index = ValidIndex()
        self._close_run()
        return out

    # -- the scanner -------------------------------------------------------------

    def _scan(self, buf: bytes, pos: int, out: list[Item], *, final: bool) -> int:
        """Parse ``buf`` from ``pos``; append items to ``out``; return where to resume."""
        n = len(buf)
        la_first = self._la_first
        la_second = self._la_second
        judge = self._judge
        parse_at = judge.parse_at
        discard = self._discard
        stats = self.stats
        # The next header that may start a frame (protocol/candidates.py): headers whose
        # command bytes no frame carries are skipped in C, as part of the garbage.
        find = judge.finder.find
        event_run = _EVENT_RUN
        reasons = REASONS
        while pos < n:
            if buf[pos] == la_first and pos + 1 < n and buf[pos + 1] == la_second:
                pos = self._scan_la_only(buf, pos, out)
                if pos >= n:
                    break
            p = find(buf, pos)
            if p < 0:
                break
            if p > pos:
                discard(out, buf[pos:p], "garbage")
            state, size, item = parse_at(buf, p, final)
            if state == COMPLETE:
                assert item is not None
                if type(item) is Frame:
                    out.append(item)
                    stats.frames += 1
                    pos = p + size
                else:
                    # A run of ``EE DD`` is a run of events (each pair ends where the next
                    # may start): taken at once, not a verdict per pair.
                    run = event_run(buf, p)
                    pos = run.end() if run else p + 2
                    count = (pos - p) >> 1
                    out += repeat(item, count)
                    stats.events += count
            elif state == INCOMPLETE:
                later = judge.later_valid_frame(buf, p + 1)
                if later < 0:
                    return p
                discard(out, buf[p:later], "header without its frame")
                pos = later
            elif state == WAIT:
                return p
            else:
                end = judge.unexpected_run(buf, p) if size == UNEXPECTED else p + 1
                discard(out, buf[p:end], reasons[size])
                pos = end
        if pos >= n:
            return n
        # No header in buf[pos:]: keep a last byte that may be the first half of one.
        keep = n - 1 if buf[n - 1] in HEADER_FIRST_BYTES and not final else n
        if keep > pos:
            self._discard(out, buf[pos:keep], "garbage")
        return keep

    def _scan_la_only(self, buf: bytes, pos: int, out: list[Item]) -> int:
        """Fast path for a stream of LA frames only: one find and one sum per frame.

        Returns at the first position it does not settle by itself (garbage, a bad
        frame, an incomplete tail); the general loop takes over from there.
        """
        header = self._judge.headers[0]
        direction = Direction.REPLY if header == LA_REPLY_HEADER else Direction.REQUEST
        first, second = header
        max_len = LA_MAX_LEN
        la = Family.LA
        new = tuple.__new__
        append = out.append
        n = len(buf)
        count = 0
        while pos + 3 <= n and buf[pos] == first and buf[pos + 1] == second:
            length = buf[pos + 2]
            end = pos + length + 5
            if end > n or length < LA_MIN_LEN or length > max_len[buf[pos + 4]]:
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

    def _discard(self, out: list[Item], raw: bytes, reason: str) -> None:
        stats = self.stats
        size = len(raw)
        stats.discarded_bytes += size
        by_reason = stats.by_reason
        by_reason[reason] = by_reason.get(reason, 0) + size
        last = out[-1] if out else None
        if type(last) is Discarded and last[1] == reason:
            # Join the run once, when it closes: appending to it here would copy the
            # whole run at every discarded byte (quadratic in the run's length).
            run = self._run
            if run is not None and run[0] is out and run[1] == len(out) - 1:
                run[2].append(raw)
            else:
                self._close_run()
                self._run = (out, len(out) - 1, [last[0], raw], reason)
        else:
            if self._run is not None:
                self._close_run()
            stats.resyncs += 1
            out.append(_new(Discarded, (raw, reason)))

    def _close_run(self) -> None:
        """Join the parts of the open discarded run into its item."""
        run = self._run
        if run is not None:
            out, index, parts, reason = run
            out[index] = Discarded(b"".join(parts), reason)
            self._run = None
