"""The in-memory link: delivery modes, order, unplug/plug, close, echo removal, registry."""

from __future__ import annotations

import asyncio

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.errors import BusClosedError, LocalProtocolError
from motorbus.transport import (
    DELIVERY_MODES,
    MemoryPeer,
    MemoryTransport,
    memory_pair,
    open_transport,
    register_memory_link,
    registered_memory_links,
    unregister_memory_link,
)
from motorbus.transport.memory import RANDOM_CHUNK_MAX, Delivery
from tests.transport.recorder import WAIT_S, Recorder


async def open_pair() -> tuple[Recorder, MemoryTransport, MemoryPeer]:
    transport, peer = memory_pair()
    host = Recorder()
    await transport.open(host.on_data, host.on_lost)
    return host, transport, peer


@pytest.mark.parametrize("delivery", DELIVERY_MODES)
async def test_peer_to_host_preserves_bytes_and_order(delivery: Delivery) -> None:
    transport, peer = memory_pair(delivery=delivery, seed=7)
    host = Recorder()
    await transport.open(host.on_data, host.on_lost)
    messages = [b"\x55\xaa\x03\x01", b"\xff", bytes(range(40)), b"\xee\xdd"]
    expected = b"".join(messages)
    for m in messages:
        peer.send(m)
    assert host.chunks == []  # delivered by call_soon, never inside send()
    await host.wait_for(lambda: len(host.received) >= len(expected))
    assert host.received == expected
    assert all(host.chunks)
    if delivery == "whole":
        assert host.chunks == messages
    elif delivery == "bytewise":
        assert [len(c) for c in host.chunks] == [1] * len(expected)
    else:
        assert max(len(c) for c in host.chunks) <= RANDOM_CHUNK_MAX
        assert len(host.chunks) > len(messages)
    assert transport.stats.bytes_in == len(expected)


async def test_random_delivery_is_reproducible_from_the_seed() -> None:
    cuts = []
    for _ in range(2):
        transport, peer = memory_pair(delivery="random", seed=42)
        host = Recorder()
        await transport.open(host.on_data, host.on_lost)
        peer.send(bytes(100))
        await host.wait_for(lambda h=host: len(h.received) == 100)
        cuts.append([len(c) for c in host.chunks])
    assert cuts[0] == cuts[1]


@settings(max_examples=40)
@given(
    messages=st.lists(st.binary(min_size=1, max_size=30), min_size=1, max_size=8),
    delivery=st.sampled_from(DELIVERY_MODES),
    seed=st.integers(0, 2**16),
)
def test_any_messages_arrive_whole_and_in_order(
    messages: list[bytes], delivery: Delivery, seed: int
) -> None:
    async def run() -> bytes:
        transport, peer = memory_pair(delivery=delivery, seed=seed)
        host = Recorder()
        await transport.open(host.on_data, host.on_lost)
        for m in messages:
            peer.send(m)
        total = sum(map(len, messages))
        await host.wait_for(lambda: len(host.received) >= total)
        return host.received

    assert asyncio.run(run()) == b"".join(messages)


async def test_host_writes_reach_the_peer_in_order_after_the_write_returns() -> None:
    transport, peer = memory_pair()
    got: list[bytes] = []
    arrived = asyncio.Event()

    def receive(data: bytes) -> None:
        got.append(data)
        if len(got) == 3:
            arrived.set()

    peer.set_receiver(receive)
    host = Recorder()
    await transport.open(host.on_data, host.on_lost)
    for chunk in (b"\x01", b"\x02\x03", b"\x04"):
        transport.write(chunk)
    assert got == []
    await asyncio.wait_for(arrived.wait(), WAIT_S)
    assert got == [b"\x01", b"\x02\x03", b"\x04"]
    assert transport.stats.bytes_out == 4


async def test_unplug_reports_loss_after_queued_bytes_and_blocks_open_until_plug() -> None:
    transport, peer = memory_pair()
    host = Recorder()
    await transport.open(host.on_data, host.on_lost)
    peer.send(b"\x01\x02")
    peer.unplug()
    assert not peer.connected
    await host.wait_for(lambda: host.lost)
    assert host.received == b"\x01\x02"
    assert len(host.lost) == 1
    assert isinstance(host.lost[0], BusClosedError)
    assert not transport.is_open
    with pytest.raises(BusClosedError):
        transport.write(b"\x00")
    with pytest.raises(OSError, match="unplugged"):
        await transport.open(host.on_data, host.on_lost)
    peer.send(b"\x09")  # nobody listens: dropped and counted
    assert peer.dropped_bytes == 1

    peer.plug()
    host2 = Recorder()
    await transport.open(host2.on_data, host2.on_lost)
    peer.send(b"\x03")
    await host2.wait_for(lambda: host2.received)
    assert host2.received == b"\x03"
    assert host.lost and len(host.lost) == 1  # once per open


async def test_unplug_passes_the_given_exception() -> None:
    host, _, peer = await open_pair()
    cause = OSError(5, "EIO")
    peer.unplug(cause)
    await host.wait_for(lambda: host.lost)
    assert host.lost == [cause]


async def test_close_is_idempotent_drops_queued_bytes_and_never_reports_loss() -> None:
    transport, peer = memory_pair()
    host = Recorder()
    await transport.open(host.on_data, host.on_lost)
    peer.send(b"\x01\x02")
    await transport.close()
    await transport.close()
    assert not transport.is_open
    with pytest.raises(BusClosedError):
        transport.write(b"\x00")
    peer.unplug()
    # A fresh open proves the queued callbacks ran (FIFO) without reaching the old host.
    peer.plug()
    host2 = Recorder()
    await transport.open(host2.on_data, host2.on_lost)
    peer.send(b"\x07")
    await host2.wait_for(lambda: host2.received)
    assert host.chunks == [] and host.lost == []
    assert host2.received == b"\x07"
    assert peer.dropped_bytes == 2


async def test_open_twice_is_refused() -> None:
    host, transport, _ = await open_pair()
    with pytest.raises(LocalProtocolError, match="already open"):
        await transport.open(host.on_data, host.on_lost)


async def test_echo_of_our_writes_is_removed_and_counted() -> None:
    transport, peer = memory_pair(delivery="bytewise", remove_echo=True)
    # An adapter that echoes every transmitted byte, then the device's reply.
    peer.set_receiver(lambda data: peer.send(data + b"\xaa\x55"))
    host = Recorder()
    await transport.open(host.on_data, host.on_lost)
    transport.write(b"\x55\xaa\x03")
    await host.wait_for(lambda: len(host.received) >= 2)
    assert host.received == b"\xaa\x55"
    assert transport.stats.echo_bytes_removed == 3
    assert transport.stats.bytes_in == 5


def test_unknown_delivery_mode_is_refused() -> None:
    with pytest.raises(LocalProtocolError, match="delivery='chunky'"):
        memory_pair(delivery="chunky")  # type: ignore[arg-type]


def test_registry_resolves_memory_urls() -> None:
    transport, _ = memory_pair()
    register_memory_link("bench-a", transport)
    try:
        assert "bench-a" in registered_memory_links()
        assert open_transport("memory://bench-a", baudrate=9600) is transport
    finally:
        unregister_memory_link("bench-a")
    with pytest.raises(LocalProtocolError, match="no memory link named 'bench-a'"):
        open_transport("memory://bench-a", baudrate=9600)


@pytest.mark.parametrize("name", ["", "a://b", 3])
def test_registry_refuses_bad_names(name: object) -> None:
    transport, _ = memory_pair()
    with pytest.raises(LocalProtocolError, match="name="):
        register_memory_link(name, transport)  # type: ignore[arg-type]
