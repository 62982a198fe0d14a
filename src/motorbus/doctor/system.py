"""What ``motorbus doctor`` reads from the system: sysfs, /proc, rlimits, the port's flags.

Plain functions, no asyncio; every path root (``sysfs``, ``proc``) can be pointed at a
fake tree.  The verdicts are in :mod:`motorbus.doctor.checks` and
:mod:`motorbus.doctor.host`.
"""

from __future__ import annotations

import fcntl
import glob
import grp
import os
import resource
import stat
import struct
from collections.abc import Iterable

from motorbus.doctor.checks import LatencyFacts, PortFacts, UsbInfo
from motorbus.doctor.host import HostFacts
from motorbus.transport import serial as serial_transport
from motorbus.transport import usb
from motorbus.transport.serial import usb_serial_name

__all__ = ["holders", "host_facts", "latency_facts", "port_facts", "usb_info"]

#: ``ioctl`` TIOCGSERIAL / TIOCSSERIAL and the ``ASYNC_LOW_LATENCY`` flag (linux/tty_flags.h).
_TIOCGSERIAL = 0x541E
_ASYNC_LOW_LATENCY = 1 << 13
_SERIAL_STRUCT_SIZE = 72
_SERIAL_FLAGS_OFFSET = 16  # int type, int line, unsigned port, int irq, int flags
#: A memory lock limit this large lets ``--realtime`` lock the process.
_MEMLOCK_ENOUGH = 256 << 20
_CAP_SYS_NICE = 23
_CAP_IPC_LOCK = 14


def _read(path: str) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.read().strip()
    except OSError:
        return ""


def usb_info(tty_name: str, sysfs: str = "/sys") -> UsbInfo | None:
    """The USB device behind ``ttyUSB0``/``ttyACM0`` from sysfs, or None
    (read by :func:`motorbus.transport.usb.port_info`, as ``motorbus ports`` does)."""
    info = usb.port_info(tty_name, sysfs=sysfs, by_id=())
    if info is None or not info.is_usb:
        return None
    return UsbInfo(
        vid=info.vid,
        pid=info.pid,
        driver=info.driver,
        serial=info.serial,
        product=info.product,
        manufacturer=info.manufacturer,
    )


def holders(path: str, proc: str = "/proc") -> tuple[tuple[int, str], ...]:
    """Other processes that have ``path`` open, as ``(pid, name)`` (where /proc tells)."""
    found = []
    me = os.getpid()
    for entry in os.listdir(proc):
        if not entry.isdigit() or int(entry) == me:
            continue
        fd_dir = os.path.join(proc, entry, "fd")
        try:
            fds = os.listdir(fd_dir)
        except OSError:
            continue
        for fd in fds:
            try:
                target = os.readlink(os.path.join(fd_dir, fd))
            except OSError:
                continue
            if target == path:
                found.append((int(entry), _read(os.path.join(proc, entry, "comm")) or "?"))
                break
    return tuple(found)


def port_facts(
    url: str,
    *,
    uid: int | None = None,
    gids: Iterable[int] | None = None,
    sysfs: str = "/sys",
    proc: str = "/proc",
) -> PortFacts:
    """What the system says about a local port (``uid``/``gids``: whose access to judge)."""
    path = os.path.realpath(url)
    st = os.stat(path)
    name = os.path.basename(path)
    usb = usb_info(name, sysfs) if stat.S_ISCHR(st.st_mode) else None
    if not stat.S_ISCHR(st.st_mode):
        kind = "file"
    elif path.startswith("/dev/pts/") or name == "ptmx":
        kind = "pty"
    elif usb is not None or name.startswith(("ttyUSB", "ttyACM")):
        kind = "usb"
    else:
        kind = "tty"
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    return PortFacts(
        url=url,
        path=path,
        kind=kind,
        mode=st.st_mode,
        owner_uid=st.st_uid,
        group_gid=st.st_gid,
        group_name=group,
        uid=os.geteuid() if uid is None else uid,
        gids=frozenset([*os.getgroups(), os.getegid()] if gids is None else gids),
        holders=holders(path, proc),
        usb=usb,
    )


def _low_latency_flag(path: str) -> bool | None:
    """``ASYNC_LOW_LATENCY`` of a serial port (TIOCGSERIAL), None if it has none."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        buf = fcntl.ioctl(fd, _TIOCGSERIAL, bytes(_SERIAL_STRUCT_SIZE))
        (flags,) = struct.unpack_from("i", buf, _SERIAL_FLAGS_OFFSET)
        return bool(flags & _ASYNC_LOW_LATENCY)
    except OSError:
        return None
    finally:
        os.close(fd)


def latency_facts(url: str, driver: str, *, fix: bool = False) -> LatencyFacts:
    """The latency timer (the sysfs value the bus checks on open) and the low-latency flag."""
    tty = usb_serial_name(url)
    if tty is None:
        return LatencyFacts(None)
    ms = serial_transport.read_latency_timer_ms(tty)
    fixed = ""
    wrote = False
    if fix and ms is not None and ms > 1:
        path = os.path.join(serial_transport.USB_SERIAL_SYSFS, tty, "latency_timer")
        try:
            with open(path, "w", encoding="ascii") as f:
                f.write("1")
        except OSError as err:
            fixed = f"could not write {path}: {err.strerror or err}"
        else:
            fixed = f"latency_timer {ms} -> 1 ms (until the adapter is replugged)"
            wrote = True
            ms = serial_transport.read_latency_timer_ms(tty)
    flag = _low_latency_flag(os.path.realpath(url))
    return LatencyFacts(tty, driver, ms, flag, fixed, wrote)


def _capable(number: int) -> bool:
    text = _read("/proc/self/status")
    for line in text.splitlines():
        if line.startswith("CapEff:"):
            return bool(int(line.split()[1], 16) >> number & 1)
    return False


def host_facts(timer_name: str, *, sysfs: str = "/sys", proc: str = "/proc") -> HostFacts:
    """Whether real-time mode could be granted (without asking for it), governors, RT tasks."""
    root = os.geteuid() == 0
    rtprio = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
    memlock = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
    can_fifo = root or _capable(_CAP_SYS_NICE) or rtprio == resource.RLIM_INFINITY or rtprio > 0
    can_lock = (
        root
        or _capable(_CAP_IPC_LOCK)
        or memlock == resource.RLIM_INFINITY
        or memlock >= _MEMLOCK_ENOUGH
    )
    governors = frozenset(
        _read(p)
        for p in glob.glob(f"{sysfs}/devices/system/cpu/cpu[0-9]*/cpufreq/scaling_governor")
    ) - {""}
    return HostFacts(timer_name, can_fifo, can_lock, governors, _rt_processes(proc))


def _rt_processes(proc: str) -> tuple[tuple[int, str], ...]:
    """User processes (not kernel threads) under SCHED_FIFO or SCHED_RR, but this one."""
    found = []
    me = os.getpid()
    for entry in os.listdir(proc):
        if not entry.isdigit() or int(entry) == me:
            continue
        text = _read(os.path.join(proc, entry, "stat"))
        if ")" not in text:
            continue
        fields = text.rsplit(")", 1)[1].split()
        try:
            policy = int(fields[38])  # field 41 of proc(5), counted after "comm)"
        except (IndexError, ValueError):
            continue
        if policy in (1, 2) and _read(os.path.join(proc, entry, "cmdline")):
            found.append((int(entry), _read(os.path.join(proc, entry, "comm"))))
    return tuple(found)
