"""SerialTransport over real ptys and a local TCP server, with every installed backend."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import sys
import tty
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest

from motorbus.errors import BusClosedError, LocalProtocolError
from motorbus.transport import (
    BACKENDS,
    SerialTransport,
    Transport,
    available_backends,
    open_transport,
)
from motorbus.transport import serial as serial_module
from tests.transport.recorder import WAIT_S, Recorder

INSTALLED = available_backends()


class Pty:
    """A raw pseudo-terminal: the test plays the device on the master side."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)

    async def read(self, n: int) -> bytes:
        """Read exactly ``n`` bytes the transport wrote."""
        loop = asyncio.get_running_loop()
        got = bytearray()
        done = loop.create_future()

        def readable() -> None:
            got.extend(os.read(self.master, 4096))
            if len(got) >= n and not done.done():
                done.set_result(None)

        loop.add_reader(self.master, readable)
        try:
            await asyncio.wait_for(done, WAIT_S)
        finally:
            loop.remove_reader(self.master)
        return bytes(got)

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def close_master(self) -> None:
        if self.master >= 0:
            os.close(self.master)
            self.master = -1

    def close(self) -> None:
        self.close_master()
        os.close(self.slave)


@pytest.fixture
def pty() -> Iterator[Pty]:
    p = Pty()
    yield p
    p.close()


@pytest.fixture
async def echo_server() -> AsyncIterator[tuple[int, list[asyncio.StreamWriter]]]:
    """A TCP 'serial server' on 127.0.0.1 that answers each chunk upper-cased."""
    writers: list[asyncio.StreamWriter] = []

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writers.append(writer)
        while data := await reader.read(4096):
            writer.write(data.upper())
            await writer.drain()
        writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    yield port, writers
    for w in writers:
        w.close()
    server.close()
    await server.wait_closed()


def test_all_backends_are_installed_in_the_test_environment() -> None:
    assert list(BACKENDS) == INSTALLED


def test_unknown_backend_lists_the_valid_names() -> None:
    with pytest.raises(LocalProtocolError) as info:
        SerialTransport("/dev/null", baudrate=9600, backend="pyserial")
    msg = str(info.value)
    assert "backend='pyserial'" in msg
    for name in BACKENDS:
        assert name in msg
    assert info.value.field == "backend"


@pytest.mark.parametrize(
    ("backend", "module", "extra"),
    [
        ("serialx", "serialx", "motorbus[serialx]"),
        ("pyserial-asyncio", "serial_asyncio", "motorbus[pyserial-asyncio]"),
    ],
)
def test_missing_backend_names_the_pip_extra(
    monkeypatch: pytest.MonkeyPatch, backend: str, module: str, extra: str
) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # makes the import fail
    with pytest.raises(ImportError) as info:
        SerialTransport("/dev/null", baudrate=9600, backend=backend)
    assert f"pip install {extra}" in str(info.value)
    assert backend not in available_backends()


@pytest.mark.parametrize("baudrate", [0, -9600, 9600.0, True])
def test_bad_baudrate_is_refused(baudrate: object) -> None:
    with pytest.raises(LocalProtocolError, match="baudrate"):
        SerialTransport("/dev/null", baudrate=baudrate)  # type: ignore[arg-type]


def test_rs485_is_refused_with_serialx() -> None:
    with pytest.raises(LocalProtocolError, match="rs485"):
        SerialTransport("/dev/null", baudrate=9600, backend="serialx", rs485=True)


def test_open_transport_builds_serial_transports_and_checks_options() -> None:
    t = open_transport("/dev/ttyUSB9", baudrate=921600, backend="serialx", remove_echo=True)
    assert isinstance(t, SerialTransport)
    assert (t.url, t.baudrate, t.backend, t.remove_echo) == (
        "/dev/ttyUSB9",
        921600,
        "serialx",
        True,
    )
    assert not t.is_open
    with pytest.raises(LocalProtocolError, match="'parity' is not a serial transport option"):
        open_transport("/dev/ttyUSB9", baudrate=9600, parity="E")


@pytest.mark.parametrize("backend", INSTALLED)
async def test_pty_write_read_close_and_reopen(pty: Pty, backend: str) -> None:
    t = SerialTransport(pty.path, baudrate=115200, backend=backend)
    host = Recorder()
    await t.open(host.on_data, host.on_lost)
    assert t.is_open
    assert t.latency_timer_ms is None  # a pty is not a USB adapter
    if backend == "serialx":
        assert t._transport is not None
        assert t._transport.max_size == serial_module.SERIALX_MAX_READ  # type: ignore[attr-defined]
    t.write(b"\x55\xaa\x03\x01\x04")
    assert await pty.read(5) == b"\x55\xaa\x03\x01\x04"
    pty.write(b"\xaa\x55\x10\x20")
    await host.wait_for(lambda: len(host.received) >= 4)
    assert host.received == b"\xaa\x55\x10\x20"
    assert (t.stats.bytes_out, t.stats.bytes_in) == (5, 4)

    with pytest.raises(LocalProtocolError, match="already open"):
        await t.open(host.on_data, host.on_lost)
    await t.close()
    await t.close()
    assert not t.is_open
    assert host.lost == []  # a deliberate close is not a loss
    with pytest.raises(BusClosedError):
        t.write(b"\x00")

    # The port was released (serialx locks it exclusively): it opens again.
    host2 = Recorder()
    await t.open(host2.on_data, host2.on_lost)
    pty.write(b"\x01")
    await host2.wait_for(lambda: host2.received)
    assert host2.received == b"\x01"
    await t.close()


@pytest.mark.parametrize("backend", INSTALLED)
async def test_closing_the_pty_master_reports_loss_once(pty: Pty, backend: str) -> None:
    t = SerialTransport(pty.path, baudrate=9600, backend=backend)
    host = Recorder()
    await t.open(host.on_data, host.on_lost)
    pty.close_master()
    await host.wait_for(lambda: host.lost)
    assert len(host.lost) == 1
    assert isinstance(host.lost[0], OSError)
    assert not t.is_open
    with pytest.raises(BusClosedError):
        t.write(b"\x00")
    await t.close()
    assert len(host.lost) == 1


@pytest.mark.parametrize("backend", INSTALLED)
async def test_echo_removal_over_a_pty(pty: Pty, backend: str) -> None:
    t = SerialTransport(pty.path, baudrate=115200, backend=backend, remove_echo=True)
    host = Recorder()
    await t.open(host.on_data, host.on_lost)
    t.write(b"\xff\xaa\x01")
    request = await pty.read(3)
    pty.write(request + b"\xff\xaa\x02")  # echo, then a reply that starts like it
    await host.wait_for(lambda: len(host.received) >= 3)
    assert host.received == b"\xff\xaa\x02"
    assert t.stats.echo_bytes_removed == 3
    await t.close()


@pytest.mark.parametrize("backend", INSTALLED)
async def test_socket_url_round_trip_and_server_close(
    echo_server: tuple[int, list[asyncio.StreamWriter]], backend: str
) -> None:
    port, writers = echo_server
    t: Transport = open_transport(f"socket://127.0.0.1:{port}", baudrate=9600, backend=backend)
    host = Recorder()
    await t.open(host.on_data, host.on_lost)
    t.write(b"abc")
    await host.wait_for(lambda: len(host.received) >= 3)
    assert host.received == b"ABC"
    writers[0].close()
    await host.wait_for(lambda: host.lost)
    assert len(host.lost) == 1
    assert isinstance(host.lost[0], OSError)  # BusClosedError or SerialException
    await t.close()


@contextlib.asynccontextmanager
async def refusing_server(first: bytes) -> AsyncIterator[int]:
    """A TCP 'serial server' that writes ``first`` to each client and closes, as ser2net
    does when it cannot serve ("Device open failure: ...")."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(first)
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        server.close()
        await server.wait_closed()


async def _loss_from(first: bytes, backend: str) -> BaseException:
    async with refusing_server(first) as port:
        t = open_transport(f"socket://127.0.0.1:{port}", baudrate=9600, backend=backend)
        host = Recorder()
        await t.open(host.on_data, host.on_lost)
        await host.wait_for(lambda: host.lost)
        await t.close()
    assert len(host.lost) == 1
    assert host.received == first  # the bus still gets the bytes (counted as garbage)
    return host.lost[0]


#: The backends that hand over what a connection said before it closed: pyserial's
#: ``socket://`` read, which pyserial-asyncio calls for 1024 bytes, drops the bytes it
#: read when it then finds the end of the connection ("socket disconnected").
QUOTING = [b for b in INSTALLED if b != "pyserial-asyncio"]


@pytest.mark.parametrize("backend", QUOTING)
async def test_a_server_that_closes_with_a_reason_is_quoted_in_the_loss(backend: str) -> None:
    lost = await _loss_from(b"Device open failure: Value or file not found\r\n", backend)
    assert isinstance(lost, BusClosedError)
    assert 'closed the connection, saying "Device open failure: Value or file not found"' in str(
        lost
    )


@pytest.mark.parametrize(
    "first",
    [b"\xaa\x55\x11\x01Port's device already in use\r\n", b"x" * 300, b"\x00\x01"],
    ids=["binary first", "longer than a message", "binary"],
)
async def test_bytes_that_are_not_a_servers_message_are_not_quoted(first: bytes) -> None:
    lost = await _loss_from(first, "fast")
    assert "saying" not in str(lost)


@pytest.mark.parametrize("backend", INSTALLED)
async def test_missing_device_raises_oserror(tmp_path: Path, backend: str) -> None:
    t = SerialTransport(str(tmp_path / "ttyNOPE"), baudrate=9600, backend=backend)
    with pytest.raises(OSError):
        await t.open(Recorder().on_data, Recorder().on_lost)
    assert not t.is_open


async def test_rs485_on_a_port_without_it_fails_cleanly(pty: Pty) -> None:
    t = SerialTransport(pty.path, baudrate=9600, rs485=True)
    with pytest.raises(OSError, match="RS-485"):
        await t.open(Recorder().on_data, Recorder().on_lost)
    assert not t.is_open


def test_usb_serial_names_are_found_through_links(tmp_path: Path) -> None:
    device = tmp_path / "ttyUSB3"
    device.touch()
    link = tmp_path / "usb-FTDI_FT232R_A123-if00-port0"
    link.symlink_to(device)
    assert serial_module.usb_serial_name(str(link)) == "ttyUSB3"
    assert serial_module.usb_serial_name(str(device)) == "ttyUSB3"
    assert serial_module.usb_serial_name("/dev/ttyACM0") is None
    assert serial_module.usb_serial_name("socket://127.0.0.1:7012") is None


def test_latency_timer_is_read_from_sysfs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "ttyUSB0").mkdir()
    (tmp_path / "ttyUSB0" / "latency_timer").write_text("16\n")
    monkeypatch.setattr(serial_module, "USB_SERIAL_SYSFS", str(tmp_path))
    assert serial_module.read_latency_timer_ms("ttyUSB0") == 16
    assert serial_module.read_latency_timer_ms("ttyUSB1") is None


@pytest.mark.parametrize(
    ("latency_ms", "deadline_s", "warned"),
    [
        (16, 0.0008, True),
        (1, 0.0008, True),
        (1, 0.002, False),
        (16, 0.016, False),
        (None, 0.0001, False),
    ],
)
def test_warn_if_latency_exceeds(
    caplog: pytest.LogCaptureFixture, latency_ms: int | None, deadline_s: float, warned: bool
) -> None:
    t = SerialTransport("/dev/ttyUSB0", baudrate=921600)
    t.latency_timer_ms = latency_ms
    with caplog.at_level(logging.WARNING, logger="motorbus.transport"):
        assert t.warn_if_latency_exceeds(deadline_s) is warned
    records = [r for r in caplog.records if r.name == "motorbus.transport"]
    assert len(records) == int(warned)
    if warned:
        assert f"up to {latency_ms} ms" in records[0].getMessage()


@contextlib.contextmanager
def unanswered_port() -> Iterator[int]:
    """A TCP port whose connections hang: a listener with a backlog of 0, already full, so
    the kernel drops each new connection's SYN (as a host that is off the network does)
    until the listener closes; its close refuses them."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(0)
    port = listener.getsockname()[1]
    filler = socket.create_connection(("127.0.0.1", port))  # fills the backlog
    try:
        yield port
    finally:
        listener.close()
        filler.close()


@pytest.mark.parametrize("backend", INSTALLED)
async def test_opening_a_network_port_that_does_not_answer_keeps_the_loop_running(
    backend: str,
) -> None:
    # pyserial-asyncio opened the port on the event loop's thread: pyserial's connect to
    # a host that does not answer held every other bus's ticks for its 5 s timeout.
    loop = asyncio.get_running_loop()
    longest = [0.0]

    async def ticker() -> None:
        last = loop.time()
        while True:
            await asyncio.sleep(0.01)
            now = loop.time()
            longest[0] = max(longest[0], now - last)
            last = now

    with unanswered_port() as port:
        t = open_transport(f"socket://127.0.0.1:{port}", baudrate=9600, backend=backend)
        ticking = asyncio.create_task(ticker())
        opening = asyncio.create_task(t.open(Recorder().on_data, Recorder().on_lost))
        await asyncio.sleep(0.5)
        assert not opening.done()  # still connecting: the host does not answer
        opening.cancel()
        with contextlib.suppress(asyncio.CancelledError, OSError):
            await opening
        ticking.cancel()
    # A loaded machine may hold a tick up for a while, never for the connect's seconds.
    assert longest[0] < 0.4, longest[0]
    assert not t.is_open


@pytest.mark.skipif("pyserial-asyncio" not in INSTALLED, reason="pyserial-asyncio not installed")
async def test_a_connection_that_opens_after_its_open_was_cancelled_is_closed() -> None:
    # pyserial-asyncio's port is opened in a thread (the test above), which a cancel cannot
    # stop: the connection it makes afterwards must not stay open.  It would hold
    # ser2net's one client slot against the program's next try.  (fast and serialx
    # connect with asyncio, whose cancel aborts the connect itself.)
    loop = asyncio.get_running_loop()
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(0)
    listener.settimeout(5.0)  # bounded waits below
    port = listener.getsockname()[1]
    filler = socket.create_connection(("127.0.0.1", port))
    try:
        url = f"socket://127.0.0.1:{port}"
        t = open_transport(url, baudrate=9600, backend="pyserial-asyncio")
        opening = asyncio.create_task(t.open(Recorder().on_data, Recorder().on_lost))
        await asyncio.sleep(0.3)
        assert not opening.done()
        opening.cancel()
        with contextlib.suppress(asyncio.CancelledError, OSError):
            await opening
        # Room in the backlog now: the SYN the kernel dropped is sent again and accepted.
        first, _ = await loop.run_in_executor(None, listener.accept)  # the filler's
        first.close()
        late, _ = await loop.run_in_executor(None, listener.accept)  # the cancelled open's
        late.settimeout(5.0)
        with late:
            assert await loop.run_in_executor(None, late.recv, 100) == b""  # closed
        assert not t.is_open
    finally:
        filler.close()
        listener.close()
