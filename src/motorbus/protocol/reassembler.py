"""Cut frames out of a serial byte stream, resynchronising after any garbage.

Sans-I/O: ``feed(bytes)`` returns what the bytes completed - frames, the project
stepper's ``EE DD`` event, and runs of discarded bytes - and keeps the rest for the
next call.  No clock, no asyncio; it never raises on any input.

What a frame is, per family (headers, lengths, checksums, what its bytes may be), is
stated once, in ``protocol/rulebook.py``; how candidates are judged (mixed streams,
checksummed frames winning over checksum-less ones, expected reply shapes, the dump) in
``protocol/frame_judge.py``.  This module walks the stream: at each candidate header
(``protocol/candidates.py`` passes over the headers no rule lets start a frame, in C) it
takes the judge's verdict; a header whose frame is invalid costs one byte, and the search
for the next header starts at the following byte.  A header that claims more bytes than
have arrived waits for them - unless a later, complete, checksum-valid frame is already in
the buffer, which proves the header was garbage; the reassembler then skips to that frame
instead of stalling behind it.  ``EE DD`` is recognised only where a frame may start.

Work per input byte is bounded whatever the junk and however the stream is read: the
search for that later frame is kept across ``feed`` calls (``valid_index.ValidIndex``),
headers no rule allows are skipped in C, a run of ``EE DD`` events is taken at once, and
a run of discarded bytes is joined once.  Junk built to pass every rule but the checksum
costs a verdict per header.  ``tests/protocol/test_reassembler_work.py`` and
``test_reassembler_calls.py`` count the calls per byte; ``benchmarks/bench_reassembler.py``
times every kind of junk against random junk.

Accounting: the items ``feed`` returns cover the bytes it consumed contiguously and
in order (``ProjectFinishedMarker.raw`` is ``EE DD``), so the stream offset of an item is
the sum of ``len(raw)`` of the items before it; every byte fed is in a frame, an
event, a discarded run, or the buffer.  ``protocol/frames.py`` holds the items returned.
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
from motorbus.protocol.rulebook import la_sum_ok
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
        """Fast path for a stream of LA frames only: the rulebook's length bounds and
        checksum (``la_sum_ok``), one frame after another, no search.

        Returns at the first position it does not settle by itself (garbage, a bad
        frame, an incomplete tail); the general loop takes over from there.
        """
        header = self._judge.headers[0]
        direction = Direction.REPLY if header == LA_REPLY_HEADER else Direction.REQUEST
        first, second = header
        max_len = LA_MAX_LEN
        sum_ok = la_sum_ok
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
            if not sum_ok(buf, pos, end):  # the rulebook's checksum, as the judge's
                break
            append(new(Frame, (la, direction, buf[pos:end])))
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
