"""A stale reply is never given to a newer request, even when the event loop lags.

A reply that comes after its request's deadline sits in the OS's receive buffer while the
loop is busy (a long callback, a GC pause, a flood of junk to resynchronise).  If the
next request to that device is written before the loop reads those bytes, the bytes are
read after the write: by the order of reading alone they look like the new request's
reply.  The bus reads what the OS holds before each request's write, so they fall
before the request's mark and are counted as the late reply they are.

The lag is made explicit: the late reply arrives, then, in one stretch of synchronous
code (no ``await``: the loop cannot read), the late guard passes and the next request is
submitted, which an idle bus writes at once.
"""

from __future__ import annotations

import asyncio
import os
import time
import tty
from collections.abc import Iterator

import pytest

from motorbus.bus.bus import Bus
from motorbus.errors import ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.transport.memory import memory_pair
from motorbus.transport.serial import BACKENDS, SerialTransport
from tests.bus.test_bus_pty import require
from tests.fakeclock import AutojumpTimer

LATE_GUARD_S = 0.02
QUERY = la.Control(1, la.ControlAction.QUERY_STATUS)
#: The late reply to the first query, and the true reply to the second: the positions
#: tell them apart.
OLD_STATUS = la.encode_status(1, target=100, position=100)
NEW_STATUS = la.encode_status(1, target=200, position=200)


async def test_a_late_reply_the_loop_reads_after_the_next_write_is_not_its_reply() -> None:
    """In memory, on the fake clock: the late reply is queued, undelivered, at the write."""
    loop = asyncio.get_running_loop()
    timer = AutojumpTimer(loop)
    timer.start()
    host, peer = memory_pair(baudrate=921600)
    written: list[bytes] = []
    peer.set_receiver(written.append)
    try:
        async with Bus(
            host, families={Family.LA}, timer=timer, retries=0, late_guard=LATE_GUARD_S
        ) as bus:
            with pytest.raises(ReplyTimeoutError):
                await bus.request(QUERY)
            # The late reply arrives; the loop does not get round to it before the next
            # request is written (no await between the two).
            peer.send(OLD_STATUS)
            timer.advance(LATE_GUARD_S * 2)
            second = bus.submit(QUERY)
            assert bus.stats.requests == 2, "an idle bus writes at once"
            await asyncio.sleep(0)
            assert not second.done(), "the late reply to the first query was taken"
            peer.send(NEW_STATUS)
            status = await second
            assert status.position == 200
            assert bus.stats.late_replies == 1
            assert bus.stats.replies == 1
    finally:
        await timer.stop()


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    """A raw pseudo-terminal: (master fd the test plays the device on, slave path)."""
    master, slave = os.openpty()
    tty.setraw(master)
    path = os.ttyname(slave)
    try:
        yield master, path
    finally:
        os.close(master)
        os.close(slave)


async def read_frame(fd: int, size: int, timeout: float = 2.0) -> bytes:
    """Read ``size`` bytes the bus wrote (the request), or fail after ``timeout``.

    Awaits between reads: the ``pyserial-asyncio`` backend writes from a loop callback.
    """
    got = b""
    end = time.monotonic() + timeout
    os.set_blocking(fd, False)
    while len(got) < size:
        try:
            got += os.read(fd, size - len(got))
        except BlockingIOError:
            assert time.monotonic() < end, f"the bus wrote only {got.hex(' ')}"
            await asyncio.sleep(0.001)
    return got


@pytest.mark.parametrize("backend", BACKENDS)
async def test_a_late_reply_held_by_the_kernel_is_not_the_next_requests_reply(
    pty_pair: tuple[int, str], backend: str
) -> None:
    """Over a pty: the late reply is in the kernel's buffer while the loop sleeps."""
    require(backend)
    master, path = pty_pair
    transport = SerialTransport(path, baudrate=921600, backend=backend)
    async with Bus(
        transport, families={Family.LA}, retries=0, late_guard=LATE_GUARD_S, host_margin=0.01
    ) as bus:
        with pytest.raises(ReplyTimeoutError):
            await bus.request(QUERY)
        assert await read_frame(master, len(QUERY.encode())) == QUERY.encode()
        # The loop lags (this callback sleeps): the late reply reaches the kernel, the
        # late guard passes, and the next query is written before the loop reads a byte.
        os.write(master, OLD_STATUS)
        time.sleep(LATE_GUARD_S * 3)
        second = bus.submit(QUERY, timeout=2.0)
        assert bus.stats.requests == 2, "an idle bus writes at once"
        assert await read_frame(master, len(QUERY.encode())) == QUERY.encode()
        for _ in range(20):  # let the loop read whatever the kernel holds
            await asyncio.sleep(0.001)
        assert not second.done(), "the late reply to the first query was taken"
        os.write(master, NEW_STATUS)
        status = await asyncio.wait_for(second, 2.0)
        assert status.position == 200
        assert bus.stats.late_replies == 1


@pytest.mark.parametrize("backend", BACKENDS)
async def test_a_reply_in_the_kernel_before_its_deadline_is_taken_after_a_stall(
    pty_pair: tuple[int, str], backend: str
) -> None:
    """Over a pty: the device answers well inside the timeout, then the loop stalls past
    the deadline before it reads.  The reply was there when the bus looked: it is the
    reply, not a timeout (both callbacks are due at once, in whichever order the loop
    runs them), and the bus counts it as read past its deadline."""
    require(backend)
    master, path = pty_pair
    transport = SerialTransport(path, baudrate=921600, backend=backend)
    timeout = 0.05
    async with Bus(transport, families={Family.LA}, retries=0) as bus:
        pending = bus.submit(QUERY, timeout=timeout)
        assert await read_frame(master, len(QUERY.encode())) == QUERY.encode()
        os.write(master, NEW_STATUS)  # on time: the deadline is ~50 ms away
        time.sleep(timeout * 3)  # the loop stalls (no await) past the deadline
        status = await asyncio.wait_for(pending, 2.0)
        assert status.position == 200
        stats = bus.stats
        assert (stats.replies, stats.timeouts, stats.late_replies) == (1, 0, 0)
        assert stats.replies_past_deadline == 1
