"""Both ways of reaching Linux timerfd: ``os.timerfd_*`` (Python 3.13+) and ctypes on libc.

``TimerfdApi`` picks the os functions when they exist and ctypes otherwise, so on any one
interpreter only one branch runs by itself. These tests force each branch. On 3.13+ the os
branch is the real one; before 3.13 the os module has no timerfd, so the os branch is fed
stand-ins with the 3.13 signatures (keyword-only ``flags``, ``initial``, ``interval``),
built on libc. tests/test_interpreters.py runs this file under 3.11 and 3.13.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import functools
import os
import select
import sys
import time
from typing import Any

import pytest

from motorbus.bus import timerfd as timer_mod
from motorbus.bus.timer import TimerfdTimer

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="timerfd is Linux-only"
)

WAIT_S = 5.0  # generous bound for a timer due in a few milliseconds
REAL_OS_TIMERFD = hasattr(os, "timerfd_create") and hasattr(os, "timerfd_settime_ns")


class _LibcTimerfd:
    """``os.timerfd_create`` / ``os.timerfd_settime_ns`` as Python 3.13 defines them."""

    def __init__(self) -> None:
        self.libc: Any = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        self.calls: list[str] = []

    def timerfd_create(self, clockid: int, /, *, flags: int = 0) -> int:
        self.calls.append("create")
        fd = int(self.libc.timerfd_create(ctypes.c_int(clockid), ctypes.c_int(flags)))
        if fd < 0:
            raise OSError(ctypes.get_errno(), "timerfd_create")
        return fd

    def timerfd_settime_ns(
        self, fd: int, /, *, flags: int = 0, initial: int = 0, interval: int = 0
    ) -> tuple[int, int]:
        self.calls.append("settime")
        spec = timer_mod.ITimerSpec()
        spec.it_value.tv_sec, spec.it_value.tv_nsec = divmod(initial, 1_000_000_000)
        spec.it_interval.tv_sec, spec.it_interval.tv_nsec = divmod(interval, 1_000_000_000)
        if (
            self.libc.timerfd_settime(
                ctypes.c_int(fd), ctypes.c_int(flags), ctypes.byref(spec), None
            )
            < 0
        ):
            raise OSError(ctypes.get_errno(), "timerfd_settime")
        return (0, 0)


def force(branch: str, monkeypatch: pytest.MonkeyPatch) -> _LibcTimerfd | None:
    """Make the next ``TimerfdApi()`` take ``branch``; returns the stand-in, if any."""
    monkeypatch.setattr(timer_mod, "_timerfd_api", None)
    if branch == "ctypes":
        monkeypatch.delattr(os, "timerfd_create", raising=False)
        monkeypatch.delattr(os, "timerfd_settime_ns", raising=False)
        return None
    if REAL_OS_TIMERFD:
        return None
    fake = _LibcTimerfd()
    monkeypatch.setattr(os, "timerfd_create", fake.timerfd_create, raising=False)
    monkeypatch.setattr(os, "timerfd_settime_ns", fake.timerfd_settime_ns, raising=False)
    return fake


BRANCHES = ["os", "ctypes"]


@pytest.mark.parametrize("branch", BRANCHES)
def test_the_branch_is_the_one_forced(branch: str, monkeypatch: pytest.MonkeyPatch) -> None:
    force(branch, monkeypatch)
    api = timer_mod.TimerfdApi()
    assert (api._libc is None) is (branch == "os")
    assert timer_mod.api() is not api  # a fresh module-level instance, same branch
    assert (timer_mod.api()._libc is None) is (branch == "os")


@pytest.mark.parametrize("branch", BRANCHES)
def test_an_armed_fd_expires_once_and_never_early(
    branch: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake = force(branch, monkeypatch)
    api = timer_mod.TimerfdApi()
    fd = api.create()
    try:
        assert os.get_blocking(fd) is False  # TFD_NONBLOCK reached the kernel
        assert os.get_inheritable(fd) is False  # and so did TFD_CLOEXEC
        deadline_ns = time.monotonic_ns() + 5_000_000  # the timerfd clock is this one
        api.set_absolute_ns(fd, deadline_ns)
        readable, _, _ = select.select([fd], [], [], WAIT_S)
        woke_ns = time.monotonic_ns()
        assert readable == [fd], "the timerfd did not expire"
        assert woke_ns >= deadline_ns, f"expired {(deadline_ns - woke_ns) / 1e3:.0f} us early"
        assert int.from_bytes(os.read(fd, 8), sys.byteorder) == 1  # one expiry, no interval
    finally:
        os.close(fd)
    if fake is not None:
        assert fake.calls == ["create", "settime"]


@pytest.mark.parametrize("branch", BRANCHES)
def test_zero_disarms(branch: str, monkeypatch: pytest.MonkeyPatch) -> None:
    force(branch, monkeypatch)
    api = timer_mod.TimerfdApi()
    fd = api.create()
    try:
        api.set_absolute_ns(fd, time.monotonic_ns() + 20_000_000)
        api.set_absolute_ns(fd, 0)
        # A disarmed timerfd never becomes readable; 100 ms is five times the old deadline.
        assert select.select([fd], [], [], 0.1)[0] == []
        with pytest.raises(BlockingIOError):
            os.read(fd, 8)
    finally:
        os.close(fd)


@pytest.mark.parametrize("branch", BRANCHES)
def test_timerfd_timer_runs_on_each_branch(branch: str, monkeypatch: pytest.MonkeyPatch) -> None:
    force(branch, monkeypatch)
    assert timer_mod.timerfd_available()

    async def main() -> None:
        timer = TimerfdTimer()
        try:
            assert (timer._api._libc is None) is (branch == "os")
            loop = asyncio.get_running_loop()
            fired: asyncio.Future[float] = loop.create_future()
            deadlines = [timer.now() + d for d in (0.004, 0.002, 0.006)]
            order: list[float] = []

            def hit(deadline: float) -> None:
                assert timer.now() >= deadline
                order.append(deadline)
                if len(order) == len(deadlines):
                    fired.set_result(timer.now())

            for d in deadlines:
                timer.call_at(d, functools.partial(hit, d))
            await asyncio.wait_for(fired, WAIT_S)
            assert order == sorted(deadlines)
        finally:
            timer.close()

    asyncio.run(main())
