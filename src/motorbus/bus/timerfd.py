"""Linux ``timerfd``: the two syscalls :class:`motorbus.bus.timer.TimerfdTimer` arms its
wake-up source with, through the os module (Python 3.13+) or ctypes on libc.

Only the syscalls live here; the timer's rules (never early, one arming for a loop
turn's changes) are ``motorbus.bus.timer``'s.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from typing import Any

__all__ = ["TimerfdApi", "api", "timerfd_available"]

# Linux ABI constants, timerfd_create(2) and <linux/time.h>.
_CLOCK_MONOTONIC = 1  # the clock time.monotonic() reads on Linux
_TFD_TIMER_ABSTIME = 1  # timerfd_settime(2): new_value is an absolute time
_TFD_NONBLOCK = os.O_NONBLOCK  # timerfd_create(2): same value as O_NONBLOCK
_TFD_CLOEXEC = getattr(os, "O_CLOEXEC", 0)  # timerfd_create(2): same value as O_CLOEXEC
_NS_PER_S = 1_000_000_000


class TimerfdApi:
    """``timerfd_create`` / ``timerfd_settime``: the os module (3.13+) or ctypes on libc."""

    def __init__(self) -> None:
        self._os_create: Any = getattr(os, "timerfd_create", None)
        self._os_settime_ns: Any = getattr(os, "timerfd_settime_ns", None)
        self._libc: Any = None
        if self._os_create is None or self._os_settime_ns is None:
            libc_name = ctypes.util.find_library("c")
            self._libc = ctypes.CDLL(libc_name, use_errno=True)
            self._libc.timerfd_create.argtypes = (ctypes.c_int, ctypes.c_int)
            self._libc.timerfd_create.restype = ctypes.c_int
            self._libc.timerfd_settime.argtypes = (
                ctypes.c_int,
                ctypes.c_int,
                ctypes.POINTER(ITimerSpec),
                ctypes.c_void_p,
            )
            self._libc.timerfd_settime.restype = ctypes.c_int
            self._settime = self._libc.timerfd_settime
        self._specs: dict[int, tuple[ITimerSpec, Any]] = {}

    def create(self) -> int:
        flags = _TFD_NONBLOCK | _TFD_CLOEXEC
        if self._libc is None:
            return int(self._os_create(_CLOCK_MONOTONIC, flags=flags))
        fd = int(self._libc.timerfd_create(_CLOCK_MONOTONIC, flags))
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_create: {os.strerror(err)}")
        return fd

    def set_absolute_ns(self, fd: int, deadline_ns: int) -> None:
        """Arm ``fd`` to expire once at ``deadline_ns`` (0 disarms it)."""
        if self._libc is None:
            self._os_settime_ns(fd, flags=_TFD_TIMER_ABSTIME, initial=deadline_ns, interval=0)
            return
        # Called several times a tick: one preallocated struct per fd (each timer, and so
        # each loop and thread, has its own fd), no per-call objects.
        try:
            found = self._specs[fd]
        except KeyError:
            spec = ITimerSpec()
            found = self._specs[fd] = (spec, ctypes.byref(spec))
        value = found[0].it_value
        value.tv_sec = deadline_ns // _NS_PER_S
        value.tv_nsec = deadline_ns % _NS_PER_S
        if self._settime(fd, _TFD_TIMER_ABSTIME, found[1], None) < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_settime: {os.strerror(err)}")


class TimeSpec(ctypes.Structure):
    # struct timespec: time_t and long are both the C long on Linux's LP64 and ILP32 ABIs.
    _fields_ = (("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long))


class ITimerSpec(ctypes.Structure):
    _fields_ = (("it_interval", TimeSpec), ("it_value", TimeSpec))


_timerfd_api: TimerfdApi | None = None


def api() -> TimerfdApi:
    """The process's one ``TimerfdApi`` (made at first use)."""
    global _timerfd_api
    if _timerfd_api is None:
        _timerfd_api = TimerfdApi()
    return _timerfd_api


def timerfd_available() -> bool:
    """Return True if this platform offers Linux ``timerfd``."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        fd = api().create()
    except (OSError, AttributeError):
        return False
    os.close(fd)
    return True
