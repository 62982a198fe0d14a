"""Writes straight on a pyserial port's file descriptor: one ``os.write`` a frame.

pyserial's non-blocking ``write`` retries ``os.write`` in a busy loop while the output
buffer is full, which holds the event loop, and every bus on it, until the port drains
(a device that stopped reading, an adapter that stalls): one port whose device stopped
reading stalled every bus of the loop, stop commands included
(``tests/transport/test_direct_io.py``).  :func:`install` gives one opened port a
``write`` with pyserial's contract, minus the spin: one ``os.write``, returning how much
it took; a full output buffer raises ``BlockingIOError``, which the ``"fast"`` backend
answers by buffering the rest and waiting until the port is writable.

Reads stay pyserial's: a replacement saved a ``select`` a read, a CPU saving no published
figure needs (issue 40; benchmarks/README.md has the measurement).

Only a local device opened by pyserial's own POSIX class qualifies: a ``socket://`` or
``rfc2217://`` port, another platform or a subclass keeps pyserial's ``write``.
"""

from __future__ import annotations

import os
from typing import Any

__all__ = ["install"]


def _posix_serial_class() -> type | None:
    try:
        from serial import serialposix
    except ImportError:  # not a POSIX platform
        return None
    cls: type = serialposix.Serial
    return cls


def install(port: Any) -> bool:
    """Give the opened pyserial ``port`` a direct ``write`` (module docstring).

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

    def write(data: bytes | bytearray | memoryview) -> int:
        fd = fd_of()
        try:
            return os.write(fd, data)
        except (BlockingIOError, InterruptedError):
            raise  # the backend keeps the frame and waits until the port is writable
        except OSError as err:
            raise SerialException(f"write failed: {err}") from err

    ser.write = write
    return True
