"""One process, one port: a serial port opens with an exclusive lock unless ``share=True``.

Two readers of one port each get part of the replies (issue 19 case 5: 40 of 80
requests failed with two buses on one port), so a second open is refused, naming the
holder where the system tells, whatever the backend of either open.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import textwrap
import tty
from collections.abc import Iterator
from pathlib import Path

import pytest

from motorbus.bus.bus import Bus
from motorbus.devices.la import InspireLA
from motorbus.errors import PortInUseError
from motorbus.protocol.base import Family
from motorbus.sim.la import LAModel
from motorbus.sim.pty import PtySim
from motorbus.transport.serial import (
    BACKENDS,
    SerialTransport,
    open_transport,
    port_lock_holders,
)

LA_BAUD = 921600
HOST_MARGIN_S = 0.05
#: Longest wait for the helper process to hold the port.
READY_S = 30.0


def _ignore(*_args: object) -> None:
    return None


@pytest.fixture
def pty_path() -> Iterator[str]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    try:
        yield os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("second", BACKENDS)
@pytest.mark.parametrize("first", BACKENDS)
async def test_a_second_open_is_refused_naming_this_process(
    pty_path: str, first: str, second: str
) -> None:
    holder = SerialTransport(pty_path, baudrate=LA_BAUD, backend=first)
    await holder.open(_ignore, _ignore)
    try:
        other = SerialTransport(pty_path, baudrate=LA_BAUD, backend=second)
        with pytest.raises(PortInUseError) as info:
            await other.open(_ignore, _ignore)
        err = info.value
        assert isinstance(err, OSError)  # ``except OSError`` still catches it
        assert str(err).startswith(f"{pty_path} is in use by PID {os.getpid()} (this process)")
        assert "share=True" in str(err)
        assert err.holders and err.holders[0][0] == os.getpid()
        assert not other.is_open
        # share=True opts out of the lock: it opens beside the holder.
        shared = SerialTransport(pty_path, baudrate=LA_BAUD, backend=second, share=True)
        await shared.open(_ignore, _ignore)
        assert shared.is_open
        await shared.close()
    finally:
        await holder.close()
    # Closed: the lock is gone and the port opens again.
    again = SerialTransport(pty_path, baudrate=LA_BAUD, backend=second)
    await again.open(_ignore, _ignore)
    await again.close()


@pytest.mark.parametrize("backend", BACKENDS)
async def test_two_buses_on_one_pty_the_second_is_refused(backend: str) -> None:
    with PtySim([LAModel(1)], baud=LA_BAUD) as sim:
        first = Bus(
            SerialTransport(sim.path, baudrate=LA_BAUD, backend=backend),
            name="first",
            families=[Family.LA],
            host_margin=HOST_MARGIN_S,
        )
        second = Bus(
            open_transport(sim.path, baudrate=LA_BAUD, backend=backend),
            name="second",
            families=[Family.LA],
            host_margin=HOST_MARGIN_S,
            reconnect=False,
        )
        async with first:
            with pytest.raises(PortInUseError, match=rf"PID {os.getpid()} \(this process\)"):
                await second.open()
            assert second.transport.stats.bytes_out == 0  # nothing was sent
            # The first bus keeps every reply.
            la = InspireLA(first, 1)
            for _ in range(5):
                await la.status()
            assert first.stats.timeouts == 0
        assert sim.error is None


async def test_share_true_opens_a_second_bus_on_the_port() -> None:
    with PtySim([LAModel(1)], baud=LA_BAUD) as sim:
        first = Bus(
            open_transport(sim.path, baudrate=LA_BAUD),
            name="first",
            families=[Family.LA],
            host_margin=HOST_MARGIN_S,
        )
        second = Bus(
            open_transport(sim.path, baudrate=LA_BAUD, share=True),
            name="second",
            families=[Family.LA],
            host_margin=HOST_MARGIN_S,
        )
        async with first, second:
            assert first.transport.is_open and second.transport.is_open


HOLDER = textwrap.dedent(
    """
    import asyncio, sys
    from motorbus.transport.serial import SerialTransport

    async def main():
        t = SerialTransport(sys.argv[1], baudrate=921600)
        await t.open(lambda d: None, lambda e: None)
        print("holding", flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
        await t.close()

    asyncio.run(main())
    """
)


async def test_the_holder_in_another_process_is_named_with_its_command_line(
    pty_path: str, tmp_path: Path
) -> None:
    script = tmp_path / "hold_port.py"
    script.write_text(HOLDER, encoding="utf-8")
    proc = subprocess.Popen(
        [sys.executable, str(script), pty_path],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = await asyncio.wait_for(asyncio.to_thread(proc.stdout.readline), READY_S)
        assert line.strip() == "holding", "the helper process did not open the port"
        assert [pid for pid, _ in port_lock_holders(pty_path)] == [proc.pid]
        with pytest.raises(PortInUseError) as info:
            await SerialTransport(pty_path, baudrate=LA_BAUD).open(_ignore, _ignore)
        text = str(info.value)
        assert f"is in use by PID {proc.pid} (" in text, text
        assert "hold_port.py" in text, text
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        proc.wait(READY_S)


def test_holders_are_not_looked_up_for_urls_or_missing_paths(tmp_path: Path) -> None:
    assert port_lock_holders("socket://127.0.0.1:7000") == ()
    assert port_lock_holders(str(tmp_path / "missing")) == ()


def test_share_must_be_a_bool() -> None:
    with pytest.raises(ValueError, match="share"):
        SerialTransport("/dev/null", baudrate=LA_BAUD, share="yes")  # type: ignore[arg-type]
    assert open_transport("/dev/null", baudrate=LA_BAUD, share=True).share is True  # type: ignore[attr-defined]
