"""The server's buffer of a served stream's targets (``TargetFeed``), without a network:
rows by tick, replacement, the end, and what a silent client gets."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from motorbus import StreamEnded
from motorbus.serve.keys import PayloadError
from motorbus.serve.streams_server import TargetFeed
from motorbus.streaming.model import GAP_TICKS, GapPolicy
from motorbus.streaming.targets import ramp_step

P = 0.01


def tick(feed: TargetFeed, k: int) -> object:
    return feed.source(k * P, {})


def test_rows_are_served_on_their_ticks_and_the_end_ends_it() -> None:
    feed = TargetFeed((1, 2), P, GapPolicy.RAMP)
    assert tick(feed, 0) == {}  # nothing yet: nothing sent, not a gap
    assert feed.held == 0
    feed.put(1, [feed.row([10, 20], "r"), feed.row({"2": 30}, "r")], end=True)
    assert tick(feed, 1) == {1: 10, 2: 20}
    assert tick(feed, 2) == {2: 30}
    assert tick(feed, 3) is None


@pytest.mark.parametrize("rows", [[700], [700, 800, 900]], ids=["one-row", "three-rows"])
def test_ticks_skipped_past_the_end_still_serve_the_last_row(rows: list[int]) -> None:
    # The server's stream started late (or fell behind) past the last row: the rows of
    # the ticks it missed are dropped, but the last one, where the trajectory ends, goes
    # out once, as a local stream's does (it used to end having sent nothing).
    feed = TargetFeed((1,), P, GapPolicy.RAMP)
    feed.put(0, [feed.row(n, "r") for n in rows], end=True)
    assert tick(feed, len(rows) + 1) == {1: rows[-1]}
    assert tick(feed, len(rows) + 2) is None
    assert feed.unwritten == list(range(len(rows) - 1))


def test_later_rows_replace_from_their_tick_on_and_past_ticks_are_dropped() -> None:
    feed = TargetFeed((1,), P, GapPolicy.RAMP)
    feed.put(0, [feed.row(n, "r") for n in (1, 2, 3, 4)], end=True)
    assert tick(feed, 0) == {1: 1}
    feed.put(2, [feed.row(9, "r")], end=False)  # replaces ticks 2 and 3, no end now
    assert tick(feed, 1) == {1: 2}
    assert tick(feed, 2) == {1: 9}
    assert tick(feed, 3) == {}  # nothing for tick 3 any more: held, not ended
    feed.put(3, [feed.row(7, "r"), feed.row(8, "r")], end=True)  # tick 3 was served
    assert tick(feed, 4) == {1: 8}
    assert tick(feed, 5) is None
    assert feed.held == 1


@pytest.mark.parametrize("policy", [GapPolicy.RAMP, GapPolicy.STOP])
def test_a_silent_client_is_held_then_gets_its_gap_policy(policy: GapPolicy) -> None:
    feed = TargetFeed((1,), P, policy)
    feed.put(0, [feed.row(100, "r")], end=False)
    assert tick(feed, 0) == {1: 100}
    for k in range(1, GAP_TICKS):
        assert tick(feed, k) == {}
    if policy is GapPolicy.STOP:
        with pytest.raises(StreamEnded, match="client silent, 3 ticks missed"):
            tick(feed, GAP_TICKS)
        return
    for k in range(GAP_TICKS, 10):
        assert tick(feed, k) == {}  # "ramp": held until rows come again
    feed.put(10, [feed.row(500, "r")], end=False)
    assert tick(feed, 10) == {1: 500}
    assert (feed.missed, feed.held) == (0, 9)


def test_a_gap_during_the_ramp_of_an_earlier_one_ramps_on_from_where_it_got() -> None:
    # The ramp is applied to the rows as the tick serves them (``ramp_step``); a second
    # gap while it ran started a new ramp from the last row itself, so the actuators
    # jumped to their targets (CI: 500, 520, then 1500 at a ramp of 20 a tick).
    stream = SimpleNamespace(ramp=None)
    feed = TargetFeed((1,), P, GapPolicy.RAMP)
    feed.stream = stream  # type: ignore[assignment]
    feed.put(0, [feed.row(500, "r")], end=False)
    assert tick(feed, 0) == {1: 500}
    sent = []
    for k in (2, 4):  # a tick missed before each row: each a (short) gap
        assert tick(feed, k - 1) == {}
        feed.put(k, [feed.row(1500, "r")], end=False)
        row = tick(feed, k)
        assert stream.ramp is not None
        sent.append(ramp_step(stream.ramp, row, 20)[1])  # what the tick then writes
    assert sent == [520, 540]


@pytest.mark.parametrize("row", [[1, 2], "100", True, {"x": 5}, 2001, [None]])
def test_a_bad_row_is_refused_naming_rows(row: object) -> None:
    feed = TargetFeed((1,), P, GapPolicy.RAMP)
    with pytest.raises(PayloadError) as refused:
        feed.row(row, "rows[0]")
    assert refused.value.field == "rows"
