"""The tracking targets of a served stream (``rig.runner._served_targets``): row ``k`` at
``origin + k * period``, the rows the server did not write as sent left out, and a run
that lost too many (or wrote nothing) refused, naming the counts."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from motorbus.rig.runner import UNWRITTEN_SHARE, TicksMissed, _served_targets


def served(frames: int, unwritten: set[int]) -> SimpleNamespace:
    stats = SimpleNamespace(as_dict=lambda: {"frames": frames, "held": 0, "skipped": 0})
    return SimpleNamespace(origin=100.0, period=0.01, stats=stats, unwritten=frozenset(unwritten))


ROWS = [500 + k for k in range(100)]


def test_rows_are_placed_at_their_ticks_without_the_unwritten_ones() -> None:
    out = _served_targets(served(98, {3, 7, 250}), ROWS, 2.0)  # 250: past the sine
    assert len(out) == 98
    assert out[0] == (100.0, 500) and (100.0 + 4 * 0.01, 504) in out
    assert all(x not in (503, 507) for _, x in out)


def test_a_run_that_lost_too_many_ticks_is_refused_naming_them() -> None:
    lost = set(range(round(UNWRITTEN_SHARE * len(ROWS)) + 1))
    with pytest.raises(TicksMissed, match=rf"did not write {len(lost)} of the 100 ticks"):
        _served_targets(served(90, lost), ROWS, 2.0)


def test_a_run_the_server_wrote_nothing_of_fails() -> None:
    with pytest.raises(ValueError, match="wrote no target of the sine"):
        _served_targets(served(0, set()), ROWS, 0.5)
