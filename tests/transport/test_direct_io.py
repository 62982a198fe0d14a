"""Direct reads and writes on a pyserial port (``transport/direct_io.py``), over real ptys.

The contract is pyserial's, minus its per-call ``select``: a read with nothing to read
returns no bytes unless the port hung up, a hang-up or a failed read raises
``SerialException``, and a write to a full port raises ``BlockingIOError`` (pyserial's
own non-blocking write spins until the port drains), which the backend answers by
buffering.
"""

from __future__ import annotations

import asyncio
import errno
import os
import select

import pytest
import serial

from motorbus.transport import SerialTransport, direct_io
from tests.transport.recorder import Recorder
from tests.transport.test_serial_transport import Pty, pty  # noqa: F401 (fixture)


def _open(path: str) -> serial.Serial:
    port = serial.Serial(path, 921600, timeout=0, write_timeout=0)
    assert direct_io.install(port)
    return port


def test_a_read_returns_what_the_port_holds_and_nothing_when_it_holds_nothing(
    pty: Pty,  # noqa: F811
) -> None:
    port = _open(pty.path)
    try:
        assert port.read(64) == b""  # the peer is there: no bytes is no hang-up
        pty.write(b"\xaa\x55\x01")
        select.select([port.fd], [], [], 5)
        assert port.read(64) == b"\xaa\x55\x01"
        assert port.read(64) == b""
    finally:
        port.close()


def test_a_write_returns_what_the_port_took(pty: Pty) -> None:  # noqa: F811
    port = _open(pty.path)
    try:
        assert port.write(b"\x55\xaa\x03") == 3
        assert port.write(memoryview(b"\x01\x02")) == 2
        # The pty hands each write on by itself: the second may come after the first
        # is readable (it did under load), so read until both are there.
        got = b""
        while len(got) < 5 and select.select([pty.master], [], [], 5)[0]:
            got += os.read(pty.master, 16)
        assert got == b"\x55\xaa\x03\x01\x02"
    finally:
        port.close()


def test_a_port_whose_other_end_hung_up_raises_as_pyserial_does(pty: Pty) -> None:  # noqa: F811
    # The slave of a pty whose master closed reads 0 bytes and polls POLLHUP: the case
    # of an unplugged USB adapter, whose tty hung up.
    port = _open(pty.path)
    try:
        pty.close_master()
        with pytest.raises(serial.SerialException, match="returned no data"):
            port.read(64)
    finally:
        port.close()


def test_a_failed_read_raises_as_pyserial_does(
    pty: Pty,  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    port = _open(pty.path)

    def failing(fd: int, n: int) -> bytes:
        raise OSError(errno.EIO, "Input/output error")

    try:
        monkeypatch.setattr(direct_io.os, "read", failing)
        with pytest.raises(serial.SerialException, match="read failed"):
            port.read(64)
    finally:
        monkeypatch.undo()
        port.close()


def test_a_full_port_refuses_a_write_instead_of_spinning(pty: Pty) -> None:  # noqa: F811
    port = _open(pty.path)
    try:
        taken = 0
        with pytest.raises(BlockingIOError):
            for _ in range(100_000):  # nobody reads the master: the buffers fill
                taken += port.write(b"\x00" * 4096)
        assert taken > 0
    finally:
        port.close()


def test_a_closed_port_is_not_read_or_written_by_its_old_fd(pty: Pty) -> None:  # noqa: F811
    port = _open(pty.path)
    port.close()
    with pytest.raises(serial.PortNotOpenError):
        port.read(1)
    with pytest.raises(serial.PortNotOpenError):
        port.write(b"\x00")


def test_only_a_local_posix_port_qualifies() -> None:
    remote = serial.serial_for_url("socket://127.0.0.1:9", do_not_open=True)
    assert not direct_io.install(remote)  # no fd of its own: pyserial's methods stay
    assert not direct_io.install(object())


async def test_the_fast_backend_delivers_a_frame_the_full_port_held_back_once_it_drains(
    pty: Pty,  # noqa: F811
) -> None:
    """A port whose device stopped reading holds its frame back, not the event loop:
    another port on the loop goes on (pyserial's own write spun until the port drained)."""
    t = SerialTransport(pty.path, baudrate=921600, backend="fast")
    host = Recorder()
    await t.open(host.on_data, host.on_lost)
    other_pty = Pty()
    other = SerialTransport(other_pty.path, baudrate=921600, backend="fast")
    other_host = Recorder()
    await other.open(other_host.on_data, other_host.on_lost)
    try:
        port = t._transport.get_extra_info("serial")  # type: ignore[union-attr]
        assert port.read.__module__ == direct_io.__name__  # the default backend uses it
        # Fill the port's output until it refuses, as a device that stopped reading.
        filler = b"\x00" * 4096
        sent = 0
        while True:
            try:
                sent += port.write(filler)
            except BlockingIOError:
                break
        t.write(b"\x55\xaa\x7e")  # held by the backend, not lost and not spun on
        other.write(b"\x55\xaa\x01")  # meanwhile, another bus of the loop talks
        assert await other_pty.read(3) == b"\x55\xaa\x01"
        other_pty.write(b"\xaa\x55\x01")
        await other_host.wait_for(lambda: other_host.received == b"\xaa\x55\x01")
        got = await pty.read(sent + 3)  # the device reads again
        assert got.endswith(b"\x55\xaa\x7e") and len(got) == sent + 3
        pty.write(b"\xaa\x55")
        await host.wait_for(lambda: host.received == b"\xaa\x55")
        assert host.lost == [] and other_host.lost == []
    finally:
        await t.close()
        await other.close()
        other_pty.close()


@pytest.mark.parametrize("backend", ["pyserial-asyncio", "serialx"])
async def test_other_backends_keep_their_own_reads(pty: Pty, backend: str) -> None:  # noqa: F811
    from motorbus.transport import available_backends

    if backend not in available_backends():
        pytest.skip(f"{backend} not installed")
    t = SerialTransport(pty.path, baudrate=921600, backend=backend)
    host = Recorder()
    await t.open(host.on_data, host.on_lost)
    try:
        port = t._transport.get_extra_info("serial")  # type: ignore[union-attr]
        read = getattr(port, "read", None)
        assert read is None or getattr(read, "__module__", "") != direct_io.__name__
        pty.write(b"\xaa\x55")
        await host.wait_for(lambda: host.received == b"\xaa\x55")
    finally:
        await t.close()
    await asyncio.sleep(0)
