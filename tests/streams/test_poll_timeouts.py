"""A stream's status polls are patient: a poll that gets no reply is counted as a poll
timeout - not a feedback timeout, and never raised.

Before, ``_poll`` counted a failed poll in ``feedback_timeouts``: a stream with
``feedback=False, poll_status=True`` reported "4 feedback timeouts" that were poll
timeouts (issue 41, point 6).  The stream went on then too; this checks it still does.
"""

from __future__ import annotations

import asyncio

from motorbus.devices.la import InspireLA
from motorbus.sim.la import LAModel
from motorbus.streams import Streamer, StreamStats
from tests.helpers import sim_bus

TICKS = 40


async def test_a_silent_actuators_polls_count_as_poll_timeouts_and_the_stream_goes_on() -> None:
    # la:3 is listed but nothing answers for it: its polls time out, its targets go in
    # the broadcast like the others' (a broadcast wants no reply).
    models = [LAModel(1), LAModel(2)]
    async with sim_bus(models, host_margin=0.002) as (bus, _):
        streamer = Streamer(bus)
        actuators = [InspireLA(bus, i) for i in (1, 2, 3)]
        rows = [[1000, 1000, 1000]] * TICKS
        stream = streamer.follow(actuators, rows, period=0.01, poll_status=True)
        await asyncio.wait_for(stream.wait(), 10)  # ends normally: nothing raised
        stats = stream.stats
        await streamer.close()
    # Every row was sent, or skipped (a tick a loaded machine started over a period late);
    # a skip past the end still sends the last row, a tick later.
    assert stats.ticks + stats.skipped in (TICKS, TICKS + 1) and stats.ticks > 0
    assert stats.poll_timeouts >= 1
    assert stats.feedback_timeouts == 0  # no feedback was asked for
    assert set(stream.statuses) == {1, 2}  # the answering ones were read
    assert stats.as_dict()["poll_timeouts"] == stats.poll_timeouts
    assert f"{stats.poll_timeouts} poll timeouts" in stats.summary()
    assert "0 feedback timeouts" in stats.summary()


def test_the_summary_names_poll_and_feedback_timeouts_apart() -> None:
    stats = StreamStats(ticks=10, frames=10, polls=6, poll_timeouts=4, feedback_timeouts=1)
    text = stats.summary()
    assert "polls 6 (0 skipped, 4 poll timeouts), 1 feedback timeouts" in text
    d = stats.as_dict()
    assert (d["poll_timeouts"], d["feedback_timeouts"]) == (4, 1)
