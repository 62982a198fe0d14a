"""``Bus.add_wire_tap``: every frame written and chunk read, in wire order, with the bus
clock's times (what a served bus's frame feed publishes)."""

from __future__ import annotations

from motorbus import Bus, InspireLA
from motorbus.bus.timer import default_timer
from motorbus.protocol import la
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim


async def test_a_tap_sees_each_write_then_its_reply_and_a_failing_tap_is_removed() -> None:
    async with MemorySim.start([LAModel(1), LAModel(2)], timer=default_timer()) as sim:
        bus = Bus(sim.transport, name="arm", host_margin=0.05, reconnect=False)
        seen: list[tuple[bool, bytes, float]] = []

        def tap(outgoing: bool, data: bytes, at: float) -> None:
            seen.append((outgoing, bytes(data), at))

        def broken(outgoing: bool, data: bytes, at: float) -> None:
            raise RuntimeError("a broken tap")

        async with bus:
            bus.add_wire_tap(tap)
            bus.add_wire_tap(broken)
            first = await InspireLA(bus, 1).status()
            assert bus._engine.wire_taps == [tap]  # the broken one is gone; the bus went on
            await InspireLA(bus, 2).status()
            bus.remove_wire_tap(tap)
            await InspireLA(bus, 1).status()
        assert first.id == 1
        writes = [data for out, data, _ in seen if out]
        assert writes == [
            la.Control(1, la.ControlAction.QUERY_STATUS).encode(),
            la.Control(2, la.ControlAction.QUERY_STATUS).encode(),
        ]
        # In wire order: each request, then the bytes of its reply; times never go back.
        directions = [out for out, _, _ in seen]
        assert directions[0] is True and directions.index(True, 1) > 1
        replies = b"".join(data for out, data, _ in seen if not out)
        assert replies.count(b"\xaa\x55") == 2
        times = [at for _, _, at in seen]
        assert times == sorted(times)
