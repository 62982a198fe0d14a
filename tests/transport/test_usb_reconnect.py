"""The port follows the adapter: the URL is resolved at every open, so a bus's reconnect
finds an adapter that came back under another name.

A fake sysfs (tests/transport/fake_sysfs.py) whose ``/dev/ttyUSBn`` nodes are links to
real ptys stands in for the adapter; a symlink in tmp_path stands in for udev's
``/dev/serial/by-id/...`` link.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from motorbus.bus.bus import Bus, BusState
from motorbus.bus.events import BusStateChanged
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.sim.la import LAModel
from motorbus.sim.pty import PtySim
from motorbus.transport import SerialTransport, open_transport, usb
from tests.transport.fake_sysfs import FT232R, FakeSysfs
from tests.transport.recorder import Recorder
from tests.transport.test_serial_transport import Pty

LA_BAUD = 921600
#: Upper bound on waiting for the bus to come back (a hang guard, not a timing claim).
REOPEN_BOUND_S = 5.0
PTY_HOST_MARGIN_S = 0.05


@pytest.fixture
def fake(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> FakeSysfs:
    """A fake sysfs and /dev that the resolver reads by default."""
    tree = FakeSysfs(tmp_path)
    monkeypatch.setattr(usb, "SYSFS", str(tree.sys))
    monkeypatch.setattr(usb, "DEV", str(tree.dev))
    return tree


@pytest.fixture
def ptys() -> Iterator[list[Pty]]:
    made: list[Pty] = []
    yield made
    for p in made:
        p.close()


def new_pty(ptys: list[Pty]) -> Pty:
    p = Pty()
    ptys.append(p)
    return p


def repoint(link: Path, target: str) -> None:
    """Point ``link`` at ``target`` as udev does: never a moment without a link."""
    tmp = link.with_name(f".{link.name}.tmp")
    tmp.symlink_to(target)
    os.replace(tmp, link)


@pytest.mark.parametrize("url", ["usb:serial=", "usb:0403", "usb:403:6001"])
def test_a_malformed_usb_url_is_refused_at_construction(url: str) -> None:
    with pytest.raises(LocalProtocolError, match="allowed forms") as caught:
        SerialTransport(url, baudrate=LA_BAUD)
    assert (caught.value.field, caught.value.value) == ("url", url)
    with pytest.raises(LocalProtocolError, match="allowed forms"):
        open_transport(url, baudrate=LA_BAUD)


async def test_a_usb_url_opens_its_adapter_and_follows_it_to_a_new_name(
    fake: FakeSysfs, ptys: list[Pty]
) -> None:
    first = new_pty(ptys)
    fake.plug(FT232R, "ttyUSB0", node=first.path)
    t = SerialTransport("usb:serial=A12345", baudrate=LA_BAUD)
    assert t.device == ""
    host = Recorder()
    await t.open(host.on_data, host.on_lost)
    assert t.device == str(fake.dev / "ttyUSB0")
    t.write(b"\x55\xaa")
    assert await first.read(2) == b"\x55\xaa"
    # Unplugged while held open: it comes back as ttyUSB1 on another pty.
    first.close_master()
    await host.wait_for(lambda: host.lost)
    fake.unplug("ttyUSB0")
    second = new_pty(ptys)
    fake.plug(FT232R, "ttyUSB1", node=second.path)
    await t.open(host.on_data, host.on_lost)
    assert t.device == str(fake.dev / "ttyUSB1")
    t.write(b"\x55\xbb")
    assert await second.read(2) == b"\x55\xbb"
    second.write(b"\xaa\x55")
    await host.wait_for(lambda: host.received == b"\xaa\x55")
    await t.close()


async def test_no_adapter_at_open_is_an_os_error_and_nothing_is_opened(
    fake: FakeSysfs,
) -> None:
    t = SerialTransport("usb:serial=A12345", baudrate=LA_BAUD)
    host = Recorder()
    with pytest.raises(OSError, match="no USB serial adapter matches usb:serial=A12345"):
        await t.open(host.on_data, host.on_lost)
    assert not t.is_open and t.device == ""


async def test_a_pty_simulator_url_is_opened_as_given(ptys: list[Pty]) -> None:
    p = new_pty(ptys)
    t = SerialTransport(p.path, baudrate=LA_BAUD)
    host = Recorder()
    await t.open(host.on_data, host.on_lost)
    assert (t.url, t.device) == (p.path, p.path)
    t.write(b"\x01")
    assert await p.read(1) == b"\x01"
    await t.close()


async def status(bus: Bus, ident: int = 1) -> int:
    reply = await bus.request(la.Control(ident, la.ControlAction.QUERY_STATUS))
    return int(reply.id)


async def test_a_bus_reconnects_to_the_adapter_under_its_new_name(fake: FakeSysfs) -> None:
    """A real Bus over a simulator: the adapter vanishes, the reconnect attempts find
    nothing (and retry), it comes back as ttyUSB1 on another pty, the bus follows."""
    with (
        PtySim([LAModel(1)], baud=LA_BAUD) as old_sim,
        PtySim([LAModel(1)], baud=LA_BAUD) as new_sim,
    ):
        fake.plug(FT232R, "ttyUSB0", node=old_sim.path)
        transport = SerialTransport("usb:serial=A12345", baudrate=LA_BAUD)
        async with Bus(
            transport, name="arm", families={Family.LA}, host_margin=PTY_HOST_MARGIN_S
        ) as bus:
            assert await status(bus) == 1
            assert transport.device == str(fake.dev / "ttyUSB0")
            with bus.events.subscribe(BusStateChanged) as states:
                fake.unplug("ttyUSB0")
                old_sim.stop()  # the adapter is gone: the bus loses its port
                assert (await states.next(timeout=REOPEN_BOUND_S)).state == "lost"
                # Two attempts: the first found no adapter and the bus went on trying.
                for _ in range(2):
                    assert (await states.next(timeout=REOPEN_BOUND_S)).state == "reconnecting"
                assert bus.state is BusState.LOST
                fake.plug(FT232R, "ttyUSB1", node=new_sim.path)
                await bus.wait_state(BusState.OPEN, timeout=REOPEN_BOUND_S)
            assert transport.device == str(fake.dev / "ttyUSB1")
            answered = new_sim.bus.stats.replies
            assert await status(bus) == 1
            assert new_sim.bus.stats.replies > answered  # the new pty's simulator answered
            assert (bus.stats.disconnects, bus.stats.reconnects) == (1, 1)


async def test_a_bus_on_a_by_id_link_reopens_where_the_link_points_now(
    tmp_path: Path,
) -> None:
    """udev re-points ``/dev/serial/by-id/...`` at the adapter's new node; a link in
    tmp_path, re-pointed to another pty between the loss and the reconnect, stands in."""
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    link = by_id / FT232R.by_id_name
    with (
        PtySim([LAModel(1)], baud=LA_BAUD) as old_sim,
        PtySim([LAModel(1)], baud=LA_BAUD) as new_sim,
    ):
        link.symlink_to(old_sim.path)
        transport = SerialTransport(str(link), baudrate=LA_BAUD)
        async with Bus(
            transport, name="arm", families={Family.LA}, host_margin=PTY_HOST_MARGIN_S
        ) as bus:
            assert await status(bus) == 1
            assert transport.device == old_sim.path
            with bus.events.subscribe(BusStateChanged) as states:
                repoint(link, new_sim.path)
                old_sim.stop()
                assert (await states.next(timeout=REOPEN_BOUND_S)).state == "lost"
                await bus.wait_state(BusState.OPEN, timeout=REOPEN_BOUND_S)
            assert transport.device == new_sim.path
            answered = new_sim.bus.stats.replies
            assert await status(bus) == 1
            assert new_sim.bus.stats.replies > answered  # the new pty's simulator answered
            assert (bus.stats.disconnects, bus.stats.reconnects) == (1, 1)
