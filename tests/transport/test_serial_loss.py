"""A port that vanishes under a write: the loss is reported once, with no traceback.

The pyserial-family backends hand a failed write to the event loop's exception handler
("Fatal write error on serial transport", with a traceback on stderr); the loss is
reported through ``on_lost`` anyway, and the bus logs it as one line.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import pytest

from motorbus.transport import SerialTransport, available_backends
from tests.transport.recorder import Recorder
from tests.transport.test_serial_transport import Pty, pty  # noqa: F401 (fixture)

INSTALLED = available_backends()


@pytest.mark.parametrize("backend", INSTALLED)
async def test_a_write_to_a_vanished_port_logs_one_line_and_reports_the_loss(
    pty: Pty,  # noqa: F811
    backend: str,
    caplog: pytest.LogCaptureFixture,
) -> None:
    loop = asyncio.get_running_loop()
    handled: list[dict[str, Any]] = []
    loop.set_exception_handler(lambda _loop, context: handled.append(context))
    try:
        t = SerialTransport(pty.path, baudrate=921600, backend=backend)
        host = Recorder()
        await t.open(host.on_data, host.on_lost)
        pty.close_master()
        with caplog.at_level(logging.WARNING):
            t.write(b"\x55\xaa")  # before the loop has seen the read side fail
            await host.wait_for(lambda: host.lost)
            await asyncio.sleep(0.01)
        await t.close()
    finally:
        loop.set_exception_handler(None)
    assert handled == []
    assert caplog.records == []  # the bus, given the loss, logs the one line
    assert len(host.lost) == 1 and isinstance(host.lost[0], OSError)
