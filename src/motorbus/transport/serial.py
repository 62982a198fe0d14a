"""Serial ports through one of three asyncio serial backends.

All three backends share the asyncio Protocol API
``create_serial_connection(loop, protocol_factory, url, baudrate=...)``:

* ``"fast"``: pyserial-asyncio-fast (``serial_asyncio_fast``), the default: the lowest
  round-trip latency measured on a pty.
* ``"serialx"``: serialx, its own termios code; low-latency mode and an exclusive lock by
  default.  RS-485 is refused with this backend: it exposes no pyserial object to set
  ``rs485_mode`` on (use ``"fast"``).
* ``"pyserial-asyncio"``: the original ``serial_asyncio``, unmaintained since 2021.

A backend is imported only when chosen, so a missing optional package fails at
:func:`open_transport` / :class:`SerialTransport` time, naming the pip extra to install.

Any pyserial URL works: a device path (``/dev/ttyUSB0``, ``/dev/serial/by-id/...``),
``usb:serial=A12345`` / ``usb:VID:PID[:SERIAL]`` (an adapter by its USB identity, see
:mod:`motorbus.transport.usb`), ``socket://host:port`` (a raw TCP serial server such as
ser2net), ``rfc2217://host:port``.
RFC 2217 does not work with the two pyserial-family backends (a known upstream bug), and
serialx waits for a modem-state acknowledgement that ser2net does not send for a pty;
prefer ``socket://`` with a raw-TCP ser2net port.

The URL is resolved at every :meth:`SerialTransport.open` - the first and each reconnect
of a bus: a ``usb:`` URL to the node of the adapter it names, a symlink to its device -
so an adapter that comes back under another name (``/dev/ttyUSB1`` after an unplug) is
found again; ``SerialTransport.device`` tells which node was opened.

One process, one port: a device path is opened with an exclusive lock (``flock``, the
lock pyserial's ``exclusive=True`` and serialx take, so other pyserial and serialx
programs honour it too), whatever the backend.  A second open - another program, or a
second bus in this one - fails with :class:`~motorbus.errors.PortInUseError` naming the
holder where the system tells (Linux: ``/proc/locks``): ``/dev/ttyUSB0 is in use by PID
1234 (python prog.py)``.  Two readers of one port each get part of the replies, so
sharing is never silent: ``share=True`` opts out of the lock.  The lock is advisory: a
program that opens the port without asking for it (``cat``, ``screen``) is not kept out.
"""

from __future__ import annotations

import asyncio
import errno
import importlib
import logging
import os
import select
from collections.abc import Callable, Coroutine
from typing import Any, cast

from motorbus.errors import BusClosedError, LocalProtocolError, PortInUseError
from motorbus.protocol.base import check_flag
from motorbus.transport import direct_io, usb
from motorbus.transport.base import CountingTransport, DataCallback, LostCallback, Transport
from motorbus.transport.memory import MEMORY_SCHEME, lookup_memory_link
from motorbus.validation import check_baud

__all__ = [
    "BACKENDS",
    "DEFAULT_BACKEND",
    "SerialTransport",
    "available_backends",
    "open_transport",
    "port_lock_holders",
]

_log = logging.getLogger("motorbus.transport")

#: Backend names, default first.
BACKENDS: tuple[str, ...] = ("fast", "serialx", "pyserial-asyncio")
#: The backend used unless another is chosen (lowest measured latency, maintained).
DEFAULT_BACKEND = "fast"
#: backend name -> (importable module, pip extra that installs it).
_BACKEND_MODULES: dict[str, tuple[str, str]] = {
    "fast": ("serial_asyncio_fast", "motorbus"),
    "serialx": ("serialx", "motorbus[serialx]"),
    "pyserial-asyncio": ("serial_asyncio", "motorbus[pyserial-asyncio]"),
}
#: How many of the first bytes a network connection (``socket://``, ``rfc2217://``)
#: receives are kept while they are text: a serial server that will not serve writes its
#: reason as a line of text and closes (ser2net: "Port's device already in use", "Device
#: open failure: ..."), and the loss then says so instead of only "closed".
SERVER_TEXT_MAX = 200
#: Read size for serialx: its default 256 KiB buffer costs ~15 µs a read (docs/platform.md §2)
#: while a bus reply is tens of bytes.
SERIALX_MAX_READ = 4096
#: How long close() waits for the backend to release the port before aborting it.
CLOSE_TIMEOUT_S = 1.0
#: Reads ``drain_input`` makes at most (each up to the backend's read size).
DRAIN_READS_MAX = 8
#: Where the Linux usb-serial drivers publish an adapter's receive latency timer (ms).
USB_SERIAL_SYSFS = usb.USB_SERIAL_SYSFS
#: Where Linux lists the file locks held, with the PID of each holder.
PROC_LOCKS = "/proc/locks"
#: Longest command line quoted in a "port in use" error.
HOLDER_CMDLINE_MAX = 80
#: errno values a refused exclusive lock shows as: pyserial reports flock's
#: EWOULDBLOCK (EAGAIN), serialx turns it into EBUSY.
_LOCK_ERRNOS = (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY)

_ConnectionFactory = Callable[..., Coroutine[Any, Any, tuple[asyncio.BaseTransport, Any]]]


def _check_backend(backend: object) -> str:
    if not isinstance(backend, str) or backend not in BACKENDS:
        raise LocalProtocolError(
            f"backend={backend!r} is not a serial backend: choose one of {', '.join(BACKENDS)}",
            field="backend",
            value=backend,
        )
    return backend


def _load_backend(backend: str) -> _ConnectionFactory:
    """Import ``backend`` and return its ``create_serial_connection``.

    Raises:
        LocalProtocolError: unknown backend name.
        ImportError: the backend's package is not installed (the message names the extra).
    """
    module_name, extra = _BACKEND_MODULES[_check_backend(backend)]
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise ImportError(
            f"serial backend {backend!r} needs the {module_name!r} package: pip install {extra}"
        ) from err
    if backend == "pyserial-asyncio":
        return _opened_in_a_thread(module)
    return cast(_ConnectionFactory, module.create_serial_connection)


def _opened_in_a_thread(module: Any) -> _ConnectionFactory:
    """pyserial-asyncio's connection, with the port opened in a worker thread.

    Its ``create_serial_connection`` opens the port on the event loop's thread: pyserial's
    connect for a ``socket://`` host that does not answer then held every other bus's
    ticks for its 5 s timeout.  pyserial-asyncio-fast opens in a thread too.
    """
    import serial  # a dependency of every backend

    async def connect(
        loop: asyncio.AbstractEventLoop, protocol_factory: Any, url: str, **kwargs: Any
    ) -> tuple[asyncio.BaseTransport, Any]:
        # A cancel leaves the thread to finish; a port it opens after all is closed as
        # soon as nothing holds it (pyserial's ports close themselves when freed).
        port = await loop.run_in_executor(None, lambda: serial.serial_for_url(url, **kwargs))
        return cast(
            tuple[asyncio.BaseTransport, Any],
            await module.connection_for_serial(loop, protocol_factory, port),
        )

    return connect


def available_backends() -> list[str]:
    """Return the names of the backends whose package can be imported, default first."""
    found = []
    for name in BACKENDS:
        try:
            _load_backend(name)
        except ImportError:
            continue
        found.append(name)
    return found


def usb_serial_name(url: str) -> str | None:
    """Return ``ttyUSBn`` if ``url`` is (a link to) a USB serial adapter, else None.

    ``/dev/serial/by-id/...`` links are resolved, so the right sysfs entry is found after
    a replug renumbered the adapter.
    """
    if "://" in url:
        return None
    name = os.path.basename(os.path.realpath(url))
    return name if name.startswith("ttyUSB") else None


def read_latency_timer_ms(tty_name: str) -> int | None:
    """Return the receive latency timer of a usb-serial adapter in ms, or None if unknown."""
    return usb.read_latency_timer_ms(tty_name, USB_SERIAL_SYSFS)


def is_device_path(url: str) -> bool:
    """True for a local device path (``/dev/ttyUSB0``), False for a URL (``socket://``)."""
    return "://" not in url


def port_lock_holders(url: str) -> tuple[tuple[int, str], ...]:
    """``(pid, command line)`` of each process holding a lock on the device ``url``.

    Read from ``/proc/locks`` (Linux); empty where the system does not tell (another
    OS, no ``/proc``, a URL rather than a device path).  A symlink such as
    ``/dev/serial/by-id/...`` is resolved: the lock is on the device itself.
    """
    if not is_device_path(url):
        return ()
    try:
        st = os.stat(url)
        with open(PROC_LOCKS, encoding="ascii", errors="replace") as f:
            lines = f.read().splitlines()
    except OSError:
        return ()
    want = (os.major(st.st_dev), os.minor(st.st_dev), st.st_ino)
    pids: list[int] = []
    for line in lines:
        # "1: FLOCK  ADVISORY  WRITE 1234 00:05:87 0 EOF" ("->" marks a waiter)
        fields = line.split()
        if "->" in fields or len(fields) < 6:
            continue
        try:
            major, minor, inode = fields[5].split(":")
            where = (int(major, 16), int(minor, 16), int(inode))
            pid = int(fields[4])
        except ValueError:
            continue
        if where == want and pid not in pids:
            pids.append(pid)
    return tuple((pid, _cmdline(pid)) for pid in pids)


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            raw = f.read()
    except OSError:
        return ""
    argv = [part.decode(errors="replace") for part in raw.split(b"\0") if part]
    # "python prog.py --x": the program and a script by their names, not their paths.
    argv = [os.path.basename(a) if i == 0 or a.endswith(".py") else a for i, a in enumerate(argv)]
    text = " ".join(argv)
    if len(text) > HOLDER_CMDLINE_MAX:
        text = text[: HOLDER_CMDLINE_MAX - 3] + "..."
    return text


def _is_lock_refusal(err: BaseException) -> bool:
    """True if opening failed because another open holds the port's exclusive lock."""
    text = str(err).lower()
    return (
        getattr(err, "errno", None) in _LOCK_ERRNOS
        or "exclusively lock" in text
        or "already locked" in text
    )


def port_in_use_error(url: str, holders: tuple[tuple[int, str], ...]) -> PortInUseError:
    """The error for a port whose exclusive lock another open holds, naming the holders."""
    me = os.getpid()
    named = [
        f"PID {pid}" + (" (this process)" if pid == me else f" ({cmd})" if cmd else "")
        for pid, cmd in holders
    ]
    who = " and ".join(named) if named else "another program (the system does not say which)"
    return PortInUseError(
        f"{url} is in use by {who}: one process, one port - close it there, or open with "
        "share=True (share = true in a bus file) if sharing is meant: each reader then "
        "gets part of the replies",
        url=url,
        holders=holders,
    )


class _Adapter(asyncio.Protocol):
    """Bridges one backend connection to the owner's callbacks; one per open."""

    def __init__(self, owner: SerialTransport) -> None:
        self.owner = owner
        self.active = True  # False once the owner closed or lost this connection
        self.lost: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def data_received(self, data: bytes) -> None:
        if self.active:
            self.owner._data_received(data)

    def eof_received(self) -> bool | None:
        return None  # let the backend close; connection_lost reports it

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.lost.done():
            self.lost.set_result(None)
        if self.active:
            self.active = False
            self.owner._connection_lost(exc)


def _report_write_errors_as_losses(transport: asyncio.Transport, url: str) -> None:
    """Keep a failed write (the port vanished) from printing an asyncio traceback.

    The pyserial-family backends hand a failed write to the event loop's exception
    handler ("Fatal write error on serial transport", a traceback on stderr), then
    abort, which reports the loss through ``connection_lost``: our ``on_lost``, which
    the bus logs as one line ("bus ... lost its port (...: write failed ...)") before
    reconnecting.  The report is all that is replaced; the abort still runs.
    """
    abort = getattr(transport, "_abort", None)
    if abort is None or not hasattr(transport, "_fatal_error"):
        return  # a backend without that path (serialx) reports losses itself

    def fatal_error(exc: BaseException, message: str = "fatal error") -> None:
        _log.debug("%s: %s: %r", url, message, exc)
        abort(exc)

    transport._fatal_error = fatal_error


class SerialTransport(CountingTransport):
    """A serial port (or serial-over-TCP URL) through an asyncio serial backend.

    Attributes:
        latency_timer_ms: the adapter's receive latency timer read back from sysfs after
            opening a USB serial adapter, else None.  The adapter holds received bytes up
            to this long, so it bounds every reply timeout from below.
    """

    def __init__(
        self,
        url: str,
        *,
        baudrate: int,
        backend: str = DEFAULT_BACKEND,
        rs485: bool = False,
        remove_echo: bool = False,
        low_latency: bool = True,
        share: bool = False,
    ) -> None:
        """Describe a port; nothing is opened until :meth:`open`.

        Args:
            url: a device path, ``usb:`` URL (checked here, resolved at each open) or
                pyserial URL (``socket://host:port``, ...).
            baudrate: line speed in bits per second (passed to every backend).
            backend: one of :data:`BACKENDS`.
            rs485: let the kernel drive the RS-485 direction line (TIOCSRS485).
            remove_echo: drop the local echo of a half-duplex adapter.
            low_latency: ask a USB serial driver for its shortest latency timer.
            share: open without the exclusive lock, so that other programs (or buses)
                may open the port too.  Off by default: two readers of one port each
                get part of the replies.

        Raises:
            LocalProtocolError: unknown backend, bad baudrate, RS-485 with serialx, or a
                malformed ``usb:`` URL.
            ImportError: the backend's package is missing (names the pip extra).
        """
        if isinstance(url, str) and usb.is_usb_url(url):
            usb.parse_usb_url(url)
        # A plausible serial rate (motorbus.validation): 10**12 used to reach the OS.
        baudrate = check_baud("baudrate", baudrate)
        rs485, remove_echo = check_flag("rs485", rs485), check_flag("remove_echo", remove_echo)
        low_latency = check_flag("low_latency", low_latency)
        share = check_flag("share", share)
        self._connect = _load_backend(backend)
        if rs485 and backend == "serialx":
            raise LocalProtocolError(
                "rs485=True is not supported with backend='serialx' (it has no pyserial "
                "rs485_mode); use backend='fast'",
                field="rs485",
                value=rs485,
            )
        super().__init__(url, baudrate, remove_echo=remove_echo)
        self.backend = backend
        self.rs485 = rs485
        self.low_latency = low_latency
        self.share = share
        self.latency_timer_ms: int | None = None
        #: The device node (or URL) the last open resolved ``url`` to; "" before.
        self.device = ""
        self._transport: asyncio.Transport | None = None
        #: ``drain_input``'s reader and fd, looked up once per opened backend transport
        #: (every request calls it: no attribute walk and fileno() call each time).
        self._drain_for: object = None
        self._drain_with: tuple[Callable[[], None] | None, Any] = (None, None)
        self._adapter: _Adapter | None = None
        self._on_data: DataCallback | None = None
        self._on_lost: LostCallback | None = None
        #: What a network connection said first, while it is text (``SERVER_TEXT_MAX``);
        #: None for a device, and from the first byte that is not text on.
        self._server_text: bytearray | None = None

    def __repr__(self) -> str:
        state = "open" if self.is_open else "closed"
        return f"SerialTransport({self.url!r}, baudrate={self.baudrate}, {self.backend}, {state})"

    @property
    def is_open(self) -> bool:
        """True between a successful :meth:`open` and :meth:`close` or loss of the port."""
        return self._transport is not None

    async def open(self, on_data: DataCallback, on_lost: LostCallback) -> None:
        """Resolve the URL afresh, open the port, apply RS-485 and low-latency settings,
        start reading.

        Raises:
            LocalProtocolError: already open.
            OSError: no USB adapter matches a ``usb:`` URL, or several do (the message
                lists them); the bus retries at its next reconnect attempt.
            PortInUseError: another open holds the port's exclusive lock (an ``OSError``
                naming the holder where the system tells); ``share=True`` opts out.
            OSError: the port cannot be opened or configured (``serial.SerialException``
                is an ``OSError``; other backend errors are wrapped in one).
        """
        self._refuse_if_open()
        loop = asyncio.get_running_loop()
        adapter = _Adapter(self)
        device = usb.resolve_port(self.url)
        if device != self.url:
            _log.debug("%s: opening %s", self.url, device)
        try:
            transport, _ = await self._connect(
                loop, lambda: adapter, device, baudrate=self.baudrate, **self._lock_options()
            )
        except OSError as err:
            if not self.share and is_device_path(device) and _is_lock_refusal(err):
                raise port_in_use_error(self.url, port_lock_holders(device)) from err
            raise
        except Exception as err:
            raise OSError(f"cannot open {self.url} with backend {self.backend!r}: {err}") from err
        self.device = device
        self._transport = cast(asyncio.Transport, transport)
        _report_write_errors_as_losses(self._transport, self.url)
        self._adapter = adapter
        self._on_data = on_data
        self._on_lost = on_lost
        self._echo.reset()
        self._server_text = None if is_device_path(device) else bytearray()
        try:
            self._configure(self._transport)
        except BaseException:
            await self.close()
            raise

    def _lock_options(self) -> dict[str, Any]:
        """The backend's exclusive-lock argument: every backend takes ``flock`` on
        ``exclusive=True`` (serialx does by default, so ``share`` must say False)."""
        if self.backend == "serialx":
            return {"exclusive": not self.share}
        if self.share or not is_device_path(self.url):
            return {}  # pyserial's default: no lock
        return {"exclusive": True}

    def _configure(self, transport: asyncio.Transport) -> None:
        """Apply the options that need the opened port."""
        if self.backend == "serialx" and hasattr(transport, "max_size"):
            transport.max_size = SERIALX_MAX_READ
        pyserial = transport.get_extra_info("serial")
        if self.backend == "fast" and is_device_path(self.device):
            direct_io.install(pyserial)  # one syscall a read and a write
        if self.rs485:
            self._set_rs485(pyserial)
        tty_name = usb_serial_name(self.device)
        if tty_name is None:
            self.latency_timer_ms = None
            return
        set_low_latency = getattr(pyserial, "set_low_latency_mode", None)
        if self.low_latency and set_low_latency is not None:
            try:
                set_low_latency(True)
            except (OSError, ValueError) as err:
                _log.warning("%s: cannot set low-latency mode: %s", self.url, err)
        self.latency_timer_ms = read_latency_timer_ms(tty_name)
        _log.debug("%s: latency timer %s ms", self.url, self.latency_timer_ms)

    def _set_rs485(self, pyserial: object) -> None:
        if pyserial is None or not hasattr(pyserial, "rs485_mode"):
            raise OSError(f"{self.url}: backend {self.backend!r} exposes no RS-485 setting")
        import serial.rs485

        try:
            pyserial.rs485_mode = serial.rs485.RS485Settings()
        except (OSError, ValueError) as err:
            raise OSError(f"{self.url}: cannot enable RS-485 mode: {err}") from err

    def warn_if_latency_exceeds(self, deadline_s: float) -> bool:
        """Log a WARNING if the adapter's latency timer makes ``deadline_s`` impossible.

        Args:
            deadline_s: the shortest reply timeout the bus will use, in seconds.

        Returns:
            True if a warning was logged (the latency timer is longer than the deadline).
        """
        ms = self.latency_timer_ms
        if ms is None or ms / 1000.0 <= deadline_s:
            return False
        _log.warning(
            "%s: the USB adapter holds received bytes up to %d ms (latency_timer), so a "
            "%.3f ms reply deadline cannot hold; set it to 1 ms (low_latency=True, or write "
            "1 to %s/%s/latency_timer) or use longer timeouts",
            self.url,
            ms,
            deadline_s * 1000.0,
            USB_SERIAL_SYSFS,
            usb_serial_name(self.device or self.url),
        )
        return True

    def write(self, data: bytes) -> None:
        """Queue ``data`` on the port; never blocks.

        Raises:
            BusClosedError: the port is not open.
        """
        data = self._outgoing(data)
        if data and self._transport is not None:
            self._transport.write(data)

    def drain_input(self) -> None:
        """Read at once what the OS already holds for the port (see ``Transport``).

        All three backends read through ``_read_ready``, the callback the loop runs when
        the port is readable (it delivers to ``on_data`` and reports a lost port as
        usual).  It is called only while ``poll`` says the port is readable (a raw
        tty read with nothing to read returns 0 bytes, which pyserial takes for a hang
        up), at most ``DRAIN_READS_MAX`` times.
        """
        transport = self._transport
        if self._drain_for is not transport:
            self._drain_for = transport
            self._drain_with = (getattr(transport, "_read_ready", None), _poller(transport))
        read_ready, poller = self._drain_with
        if read_ready is None or poller is None:
            return
        for _ in range(DRAIN_READS_MAX):
            ready = poller.poll(0)
            # POLLNVAL: the fd was closed under us (select raised EBADF here).
            if not ready or ready[0][1] & select.POLLNVAL or self._transport is not transport:
                return
            read_ready()

    async def close(self) -> None:
        """Close the port and wait (up to ``CLOSE_TIMEOUT_S``) until it is released."""
        transport, adapter = self._transport, self._adapter
        self._detach()
        if transport is None or adapter is None:
            return
        adapter.active = False
        transport.close()
        try:
            await asyncio.wait_for(asyncio.shield(adapter.lost), CLOSE_TIMEOUT_S)
        except TimeoutError:
            _log.warning(
                "%s: backend did not close within %.1f s, aborting", self.url, CLOSE_TIMEOUT_S
            )
            transport.abort()

    def _detach(self) -> None:
        self._transport = None
        self._adapter = None
        self._on_data = None
        self._on_lost = None
        self._echo.reset()

    def _data_received(self, data: bytes) -> None:
        if self._server_text is not None:
            self._hear(data)
        data = self._incoming(data)
        if data and self._on_data is not None:
            self._on_data(data)

    def _hear(self, data: bytes) -> None:
        """Keep the start of what a network connection says while it is text."""
        text = self._server_text
        assert text is not None
        text += data[: SERVER_TEXT_MAX - len(text)]
        if len(text) >= SERVER_TEXT_MAX or not _is_text(text):
            self._server_text = None  # the devices talk (or a long text): no message

    def _connection_lost(self, exc: BaseException | None) -> None:
        on_lost = self._on_lost
        said = self._server_text.decode("ascii").strip() if self._server_text else ""
        self._server_text = None
        self._detach()
        if said:
            # The server told why it closed (ser2net: the device is missing or in use).
            cause = exc
            exc = BusClosedError(f'{self.url}: the server closed the connection, saying "{said}"')
            exc.__cause__ = cause
        elif exc is None:
            # The peer closed (TCP end of file): still a loss, report it as one.
            exc = BusClosedError(f"{self.url}: the connection was closed by the other end")
        _log.debug("%s: port lost: %r", self.url, exc)
        if on_lost is not None:
            on_lost(exc)


def _is_text(data: bytes | bytearray) -> bool:
    """True if ``data`` is printable ASCII text, in lines."""
    return data.isascii() and data.translate(None, b"\r\n\t").decode("ascii").isprintable()


def _poller(transport: object) -> Any:
    """A ``select.poll`` object watching ``transport``'s fd for input, or None if the
    backend does not tell its fd (one object per opened port: ``poll(0)`` is then one
    syscall a request, cheaper than building ``select``'s fd sets each time)."""
    fd = _readable_fd(transport)
    if fd is None:
        return None
    poller = select.poll()
    poller.register(fd, select.POLLIN)
    return poller


def _readable_fd(transport: object) -> int | None:
    """The file descriptor a backend transport reads from, if it tells."""
    fd = getattr(transport, "_fileno", None)  # serialx
    if isinstance(fd, int):
        return fd
    get_extra_info = getattr(transport, "get_extra_info", None)
    pyserial = get_extra_info("serial") if get_extra_info is not None else None
    fileno = getattr(pyserial, "fileno", None)
    if fileno is None:
        return None
    try:
        fd = fileno()
    except (OSError, ValueError, AttributeError):  # pyserial raises these for URLs without one
        return None
    return fd if isinstance(fd, int) else None


def open_transport(
    url: str,
    *,
    baudrate: int,
    backend: str = DEFAULT_BACKEND,
    **opts: Any,
) -> Transport:
    """Return the transport for ``url`` (not yet opened).

    ``memory://NAME`` returns the transport registered with
    :func:`motorbus.transport.register_memory_link` (``baudrate``, ``backend`` and ``opts``
    are then ignored); anything else returns a :class:`SerialTransport`.

    Args:
        url: device path, pyserial URL or ``memory://NAME``.
        baudrate: line speed in bits per second.
        backend: serial backend name, one of :data:`BACKENDS`.
        opts: further :class:`SerialTransport` options (``rs485``, ``remove_echo``,
            ``low_latency``, ``share``).

    Raises:
        LocalProtocolError: unknown backend or option, unregistered memory link.
        ImportError: the chosen backend's package is missing.
    """
    if url.startswith(MEMORY_SCHEME):
        return lookup_memory_link(url)
    allowed = ("rs485", "remove_echo", "low_latency", "share")
    for key in opts:
        if key not in allowed:
            raise LocalProtocolError(
                f"{key!r} is not a serial transport option: choose from {', '.join(allowed)}",
                field=key,
                value=opts[key],
            )
    return SerialTransport(url, baudrate=baudrate, backend=backend, **opts)
