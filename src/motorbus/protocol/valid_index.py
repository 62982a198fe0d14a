"""Bookkeeping for the reassembler's resynchronisation: which candidate headers are valid frames.

When a header claims more bytes than have arrived, the reassembler asks whether a later,
complete, checksum-valid frame already proves it garbage.  Asking by rescanning the held
bytes at every read costs work in proportion to what is held (up to a 260-byte LA frame
of look-alike headers), not to what arrived.  :class:`ValidIndex` keeps the answers
across reads instead; the reassembler judges each candidate when it first sees it and
again only when bytes its verdict depends on arrive.  Sans-I/O, pure.
"""

from __future__ import annotations

import heapq
from bisect import bisect_left

__all__ = ["ValidIndex"]


class ValidIndex:
    """Which candidate headers are complete, checksum-valid frames: kept across feeds.

    Positions are stream offsets.  Every candidate header at ``lo <= q < to`` has been
    judged; ``valid`` lists (sorted) those that are valid now; ``due`` holds
    ``(offset, q)``: the verdict on ``q`` may change once the stream reaches ``offset``
    bytes (an LA frame's Len or its last byte arrives, or an LA frame inside a stepper
    request completes).  A header the candidate finder skips (``protocol/candidates.py``)
    counts as judged: it can never be valid.
    """

    __slots__ = ("due", "lo", "to", "valid")

    def __init__(self) -> None:
        self.lo = self.to = 0
        self.valid: list[int] = []
        self.due: list[tuple[int, int]] = []

    def restart(self, at: int) -> None:
        """Forget everything; judge again from stream offset ``at``."""
        self.lo = self.to = at
        self.valid.clear()
        self.due.clear()

    def record(self, q: int, valid: bool, due: int) -> None:
        """Note the verdict on ``q`` and when (``due`` >= 0) to judge it again."""
        if due >= 0:
            heapq.heappush(self.due, (due, q))
        if not valid and not self.valid:
            return
        i = bisect_left(self.valid, q)
        listed = i < len(self.valid) and self.valid[i] == q
        if valid and not listed:
            self.valid.insert(i, q)
        elif listed and not valid:
            del self.valid[i]

    def prune(self, base: int) -> None:
        """Drop valid positions the stream has moved past."""
        valid = self.valid
        if valid and valid[0] < base:
            del valid[: bisect_left(valid, base)]

    def forget(self, q: int) -> None:
        """``q`` is behind the stream: it is no answer any more."""
        i = bisect_left(self.valid, q)
        if i < len(self.valid) and self.valid[i] == q:
            del self.valid[i]

    def first_valid(self, s: int) -> int:
        """The first valid position at or after ``s``, or -1."""
        valid = self.valid
        i = bisect_left(valid, s)
        return valid[i] if i < len(valid) else -1
