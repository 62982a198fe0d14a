"""Reads and writes straight on a pyserial port's file descriptor: one syscall each.

pyserial's ``Serial.read`` asks ``select`` before every ``os.read`` and builds a
``Timeout``, a ``bytearray`` and a copy; its non-blocking ``write`` retries ``os.write``
in a busy loop while the output buffer is full, which holds the event loop, and every
bus on it, until the port drains (a device that stopped reading, an adapter that
stalls).  The ``"fast"`` backend calls both once per chunk and per frame.  :func:`install`
gives one opened port replacements with pyserial's contract, minus that work.  The write
is kept because with pyserial's, one port whose device stopped reading stalls every bus
of the loop, stop commands included (``tests/transport/test_direct_io.py``).  The read is
kept for the request round trip: without it, ``bench_bus.py``'s ratio to a minimal client
went from 1.094 to 1.102 (medians of four alternating pairs, 2026-12-07), across issue
40's 1.1 (benchmarks/README.md, "The direct read and the round trip"):

* ``read(size)``: one ``os.read``.  A raw tty read with nothing to read returns no bytes
  (``VMIN = 0``), as a hung-up one does, so an empty read asks ``poll`` which of the two
  it was: a hang-up (``POLLHUP``/``POLLERR``: the adapter was unplugged) raises
  ``SerialException`` as pyserial does, so the backend reports the port lost; otherwise
  it returns ``b""`` (the bytes were read already, by ``drain_input``).
* ``write(data)``: one ``os.write``, returning how much it took.  A full output buffer
  raises ``BlockingIOError``, which the backend answers by buffering the rest and waiting
  until the port is writable (instead of spinning).

Only a local device opened by pyserial's own POSIX class qualifies: a ``socket://`` or
``rfc2217://`` port, another platform or a subclass keeps pyserial's methods.
"""

from __future__ import annotations

import errno
import os
import select
from typing import Any

__all__ = ["install"]

#: errno values pyserial treats as "try again" rather than a failed port.
_RETRY_ERRNOS = frozenset({errno.EAGAIN, errno.EALREADY, errno.EWOULDBLOCK, errno.EINPROGRESS})
#: ``poll`` events that mean the port is gone (an unplugged adapter, a closed pty master).
_GONE = select.POLLHUP | select.POLLERR | select.POLLNVAL


def _posix_serial_class() -> type | None:
    try:
        from serial import serialposix
    except ImportError:  # not a POSIX platform
        return None
    cls: type = serialposix.Serial
    return cls


def install(port: Any) -> bool:
    """Give the opened pyserial ``port`` direct ``read`` and ``write`` (module docstring).

    Returns:
        True if installed; False (nothing changed) for a port that does not qualify.
    """
    cls = _posix_serial_class()
    if cls is None or type(port) is not cls:
        return False
    ser: Any = port  # (the check above narrowed ``port`` to ``object``)
    if not isinstance(ser.fd, int):
        return False
    from serial import PortNotOpenError, SerialException

    def fd_of() -> int:
        fd: int | None = ser.fd  # None once closed: never use a number another file reuses
        if fd is None:
            raise PortNotOpenError()
        return fd

    def hung_up(fd: int) -> bool:
        poller = select.poll()
        poller.register(fd, select.POLLIN)
        return any(events & _GONE for _, events in poller.poll(0))

    def read(size: int = 1) -> bytes:
        fd = fd_of()
        try:
            data = os.read(fd, size)
        except InterruptedError:
            return b""
        except OSError as err:
            if err.errno in _RETRY_ERRNOS:
                return b""
            raise SerialException(f"read failed: {err}") from err
        if not data and hung_up(fd):
            raise SerialException(
                "device reports readiness to read but returned no data "
                "(device disconnected or multiple access on port?)"
            )
        return data

    def write(data: bytes | bytearray | memoryview) -> int:
        fd = fd_of()
        try:
            return os.write(fd, data)
        except (BlockingIOError, InterruptedError):
            raise  # the backend keeps the frame and waits until the port is writable
        except OSError as err:
            raise SerialException(f"write failed: {err}") from err

    ser.read = read
    ser.write = write
    return True
