"""Unplug and replug a bus that is streaming, over the in-memory link and over a real pty.

While the port is gone: pending and queued requests fail with ``BusClosedError`` naming
the lost port, the stream task survives and skips its ticks (``stats.skipped``), and the
bus publishes ``lost`` then ``reconnecting``.  When the port is back the bus reopens
with backoff (``open``) and the stream resumes on its grid: new frames reach the models.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from motorbus.bus import engine
from motorbus.bus.bus import Bus, BusState
from motorbus.bus.events import BusStateChanged
from motorbus.devices.la import InspireLA
from motorbus.errors import BusClosedError
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.sim.bus import Pacing
from motorbus.sim.faults import FaultConfig
from motorbus.sim.la import LAModel
from motorbus.sim.pty import PtySim
from motorbus.streams import Streamer
from motorbus.transport.serial import SerialTransport
from tests.bus.test_bus_faults import eventually
from tests.helpers import PACINGS, sim_bus

PERIOD_S = 0.01
#: Upper bound on waiting for the bus to come back (a hang guard, not a timing claim).
REOPEN_BOUND_S = 5.0
LA_BAUD = 921600
PTY_HOST_MARGIN_S = 0.05


def received(models: list[LAModel]) -> int:
    return sum(len(m.received) for m in models)


def endless(ids: tuple[int, ...]) -> object:
    """A target source that never ends: tick time -> a target per actuator."""
    return lambda t, statuses: {i: 100 + (int(t * 100) + i) % 1500 for i in ids}


@pytest.mark.parametrize("pacing", PACINGS)
async def test_memory_unplug_while_streaming_then_plug(pacing: Pacing) -> None:
    ids = (1, 2, 3)
    models = [LAModel(i) for i in ids]
    async with sim_bus(models, pacing=pacing) as (bus, sim):
        streamer = Streamer(bus)
        stream = streamer.follow([InspireLA(bus, i) for i in ids], endless(ids), period=PERIOD_S)
        await eventually(lambda: received(models) >= 9, "the stream to reach the models")
        with bus.events.subscribe(BusStateChanged) as states:
            # A request to an absent ID holds the bus for up to 1 s: pending when unplugged.
            pending = asyncio.ensure_future(
                bus.request(la.Control(9, la.ControlAction.QUERY_STATUS), timeout=1.0)
            )
            await eventually(lambda: bus.stats.device("la:9").requests > 0, "la:9 sent")
            sim.peer.unplug()
            with pytest.raises(BusClosedError, match="lost its port"):
                await asyncio.wait_for(pending, REOPEN_BOUND_S)
            assert bus.state is BusState.LOST
            # Refused at once, saying why the port went (what the loss reported).
            with pytest.raises(BusClosedError, match=r"is lost \(.*: device unplugged\)$"):
                await bus.request(la.Control(1, la.ControlAction.QUERY_STATUS))
            skipped = stream.stats.skipped
            await eventually(lambda: stream.stats.skipped > skipped + 2, "ticks skipped while lost")
            assert not stream.done and streamer._task is not None and not streamer._task.done()
            before = received(models)
            sim.peer.plug()
            await bus.wait_state(BusState.OPEN, timeout=REOPEN_BOUND_S)
            seen = [e.state for e in states.pending()]
        assert seen[0] == "lost" and "reconnecting" in seen and seen[-1] == "open", seen
        assert seen.index("reconnecting") < seen.index("open")
        assert (bus.stats.disconnects, bus.stats.reconnects) == (1, 1)
        await eventually(lambda: received(models) >= before + 9, "the stream to resume")
        assert stream.error is None and not stream.done
        assert (await bus.request(la.Control(2, la.ControlAction.QUERY_STATUS))).id == 2
        await streamer.close(safe=False)


@pytest.mark.parametrize("pacing", PACINGS)
async def test_pty_disconnect_fault_reopens_same_symlink(tmp_path: Path, pacing: Pacing) -> None:
    """The pty is closed and re-created under the same symlink; the bus, given the
    symlink, reopens it and the stream resumes."""
    ids = (1, 2)
    models = [LAModel(i) for i in ids]
    link = tmp_path / "ttyLA"
    faults = FaultConfig(disconnect_after_s=0.3, reconnect_after_s=0.2, disconnect_count=1)
    before_tasks = set(asyncio.all_tasks())
    with PtySim(models, baud=LA_BAUD, faults=faults, link=link, pacing=pacing) as sim:
        transport = SerialTransport(str(link), baudrate=LA_BAUD)
        async with Bus(
            transport, name="pty", families={Family.LA}, host_margin=PTY_HOST_MARGIN_S
        ) as bus:
            streamer = Streamer(bus)
            stream = streamer.follow([InspireLA(bus, i) for i in ids], endless(ids), period=0.02)
            with bus.events.subscribe(BusStateChanged) as states:
                lost = await states.next(timeout=REOPEN_BOUND_S)
                assert lost.state == "lost"
                await bus.wait_state(BusState.OPEN, timeout=REOPEN_BOUND_S)
                seen = [lost.state, *(e.state for e in states.pending())]
            assert "reconnecting" in seen and seen[-1] == "open", seen
            before = received(models)
            await eventually(lambda: received(models) >= before + 4, "the stream to resume")
            status = await bus.request(la.Control(1, la.ControlAction.QUERY_STATUS))
            assert status.id == 1
            assert (bus.stats.disconnects, bus.stats.reconnects) == (1, 1)
            assert stream.error is None
            await streamer.close(safe=False)
        assert sim.error is None
        assert sim.bus.stats.faults_injected["disconnect"] == 1
    await asyncio.sleep(0)
    leaked = [t for t in asyncio.all_tasks() - before_tasks if not t.done()]
    assert not leaked, leaked


class FlappingServer:
    """A TCP 'serial server' that accepts each connection and closes it at once (as
    ser2net does for a second client: "Port already in use"), until told to serve:
    then it keeps the connection open, until ``drop()`` closes it."""

    def __init__(self) -> None:
        self.serving = False
        self.accepted = 0
        self.writers: list[asyncio.StreamWriter] = []

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.accepted += 1
        if not self.serving:
            writer.write(b"Port already in use\r\n")
            writer.close()
            return
        self.writers.append(writer)
        await reader.read()  # until the client goes, or drop()

    def drop(self) -> None:
        for writer in self.writers:
            writer.close()
        self.writers.clear()


async def test_a_server_that_closes_each_connection_at_once_is_retried_with_backoff(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Each reopen "succeeds" (the TCP connection opens) and is lost at once: the backoff
    # went back to its first 50 ms every time (20 reopens a second and a warning each).
    # Now it goes on growing until the port stays up for RECONNECT_STABLE_S, and a loss
    # after that starts again from the first delay.
    monkeypatch.setattr(engine, "RECONNECT_FIRST_S", 0.01)
    monkeypatch.setattr(engine, "RECONNECT_FACTOR", 4.0)
    monkeypatch.setattr(engine, "RECONNECT_MAX_S", 1.0)
    monkeypatch.setattr(engine, "RECONNECT_STABLE_S", 0.2)
    server = FlappingServer()
    listener = await asyncio.start_server(server.handle, "127.0.0.1", 0)
    port = listener.sockets[0].getsockname()[1]
    transport = SerialTransport(f"socket://127.0.0.1:{port}", baudrate=LA_BAUD)
    try:
        async with Bus(transport, families=[Family.LA]) as bus:
            # Delays 0.01, 0.04, 0.16, 0.64, then 1.0 s: five reopens in the first 1.2 s
            # at most (a slow machine makes fewer), against one every 10 ms before.
            await asyncio.sleep(1.2)
            assert 2 <= server.accepted <= 6, server.accepted
            server.serving = True
            await bus.wait_state(BusState.OPEN, timeout=REOPEN_BOUND_S)
            await asyncio.sleep(0.3)  # up for longer than RECONNECT_STABLE_S
            server.drop()
            await bus.wait_state(BusState.LOST, timeout=REOPEN_BOUND_S)
            lost = asyncio.get_running_loop().time()
            await bus.wait_state(BusState.OPEN, timeout=REOPEN_BOUND_S)
            # From the first delay again (0.01 s), not the 1 s the flapping grew it to.
            assert asyncio.get_running_loop().time() - lost < 0.5
    finally:
        server.drop()
        listener.close()
        await listener.wait_closed()
