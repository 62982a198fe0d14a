"""``StreamStats``: a line of text to print, a dict to store."""

from __future__ import annotations

import pytest

from motorbus.devices.la import InspireLA
from motorbus.errors import BusClosedError
from motorbus.protocol import la
from motorbus.streams import Streamer, StreamStats
from tests.fakeclock import rig


def test_summary_is_text_and_as_dict_has_the_same_figures() -> None:
    stats = StreamStats(ticks=300, late=2, skipped=1, frames=300, polls=40)
    stats.jitter.record(20e-6)
    text = stats.summary()
    assert isinstance(text, str)
    assert text.startswith("300 ticks (300 frames), 2 late, 1 skipped, 0 slipped; polls 40")
    d = stats.as_dict()
    assert (d["ticks"], d["late"], d["skipped"], d["polls"]) == (300, 2, 1, 40)
    assert d["jitter_max_us"] > 0


async def test_a_tick_is_timed_from_when_its_write_was_issued() -> None:
    """A write whose call takes 3 ms to return (on a server, the thread can wait for the
    GIL after the bytes went, while a Zenoh thread runs): the stream times its tick from
    when the write was issued, as a trace of the write(2) calls does (their entry), not
    from when the call returned (which counted every such tick late)."""
    async with rig(ids=range(1, 4), write_time=lambda: 3e-3) as r:
        streamer = Streamer(r.bus)
        actuators = [InspireLA(r.bus, i) for i in range(1, 4)]
        stream = streamer.follow(actuators, [[1000 + k] * 3 for k in range(20)], period=0.01)
        await stream.wait()
        await streamer.close()
    stats = stream.stats
    assert stats.ticks == 20 and stats.skipped == 0, stats.summary()
    assert stats.late == 0 and stats.slipped == 0, stats.summary()
    issued = [w.before for w in r.wire.writes if w.data[4] == la.CMD_BROADCAST_FOLLOW]
    assert len(issued) == 20
    lateness = [t - (stream.origin + k * stream.period) for k, t in enumerate(issued)]
    assert max(lateness) == pytest.approx(stats.jitter.max, abs=1e-9), (lateness, stats.summary())
    assert stats.jitter.max < 1e-4, stats.summary()


async def test_a_tick_refused_when_prepared_is_skipped_not_sent_later() -> None:
    """One send path (issue 40): a frame the bus refuses when the tick is prepared (the
    port away, the bus closing) is not prepared again at the deadline.  That tick sends
    nothing and is counted as skipped; the next one goes out as usual."""
    async with rig(ids=range(1, 4)) as r:
        streamer = Streamer(r.bus)
        actuators = [InspireLA(r.bus, i) for i in range(1, 4)]
        prepare = r.bus.prepare
        calls = [0]

        def refuse_the_third(*args: object, **kwargs: object) -> object:
            calls[0] += 1
            if calls[0] == 3:
                raise BusClosedError("refused for the test")
            return prepare(*args, **kwargs)  # type: ignore[arg-type]

        r.bus.prepare = refuse_the_third  # type: ignore[method-assign]
        stream = streamer.follow(actuators, [[1000 + k] * 3 for k in range(10)], period=0.01)
        await stream.wait()
        await streamer.close()
    stats = stream.stats
    assert calls[0] == 10, calls  # once a tick: no second try at the refused deadline
    assert (stats.ticks, stats.skipped) == (9, 1), stats.summary()
    sent = [w.data for w in r.wire.writes if w.data[4] == la.CMD_BROADCAST_FOLLOW]
    assert len(sent) == 9
    positions = [int.from_bytes(frame[6:8], "little") for frame in sent]
    assert positions == [1000, 1001, 1003, 1004, 1005, 1006, 1007, 1008, 1009]
