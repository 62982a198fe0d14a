"""``PtySim``: serve a ``SimBus`` on a real pseudo-terminal, from a dedicated thread.

Any serial client (pyserial, the motorbus bus, ser2net, minicom) opens ``sim.path``
(or the stable symlink ``sim.link``) as if it were a USB adapter.

Why a thread and not asyncio: the simulator must deliver replies at emulated wire
times with ~0.1 ms precision; ``select`` with a float timeout and ``time.monotonic``
hold that, asyncio timers on the default loop round up to a whole millisecond
(docs/platform.md section 1).

The slave end is put in raw mode and kept open by the simulator itself, so that reading
the master does not fail with EIO while no client has the device open.  A disconnect
fault closes both ends (the client sees EIO / connection lost, as on a USB unplug),
removes the symlink, and when the outage ends opens a new pty and re-points the link.

The log file (``log_file``) is a frame log (``motorbus.protocol.framelog``,
docs/frame-log.md): a header line when serving starts, then one record per frame.

The tap (``tap=PATH``) is a second pty, linked at PATH, on which the simulator writes a
copy of every byte it reads from the host and of every byte it sends back, in the order
it handles them: a listener there (``motorbus capture --port PATH``) hears the bus as a
sniffer on an RS-485 line would.  The simulator does not keep the tap's slave open, so
it can tell when nobody listens (the master polls as hung up); it then copies nothing,
and what a listener left unread is flushed when it goes, so the next one starts fresh.
What the tap could not take is counted (``tap_dropped_bytes``), never waited for.

Two options make the link misbehave as real ones do (``motorbus doctor`` is tested on
them): ``echo=True`` sends every byte the host writes straight back, as a half-duplex
RS-485 adapter whose receiver is not disabled while it transmits; ``strict_baud=True``
makes the devices deaf while the host's end of the pty is set to another rate than
``baud`` (a UART at the wrong rate reads framing errors; they answer nothing).

Two more set up actuators as a user does (``motorbus la setup``): ``device_bauds=True``
lets each LA actuator hear only at its own rate (``la:1,baud_code=0`` is a 19200 bit/s
actuator) while the host's end of the pty says which rate it speaks; ``one_at_a_time=True``
connects only the first device at start, and each :meth:`PtySim.next_device` unplugs
the present one and plugs in the next, powered up afresh (``SimBus.plug``).
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import json
import logging
import os
import select
import termios
import threading
import time
import tty
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO

from motorbus.protocol import framelog
from motorbus.sim.bus import LinkEvent, LogRecord, Pacing, SimBus
from motorbus.sim.faults import FaultConfig
from motorbus.sim.model import DeviceModel
from motorbus.sim.spec import default_baud

__all__ = ["READ_SIZE", "PtySim"]

_log = logging.getLogger("motorbus.sim")

#: Bytes read from the master per wake-up; far more than one frame (at most 260 bytes).
READ_SIZE = 4096
#: termios speed constant -> bit/s, for ``strict_baud``.
_SPEEDS = {
    getattr(termios, f"B{rate}"): rate
    for rate in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
    if hasattr(termios, f"B{rate}")
}


class PtySim:
    """Serve simulated devices on a pseudo-terminal.

    Args:
        models: the simulated devices.
        baud: emulated wire rate in bit/s; default 921600 for LA-only buses, else 9600.
        faults: faults to inject (``None``: none).
        seed: seeds turnarounds and faults (reproducible runs).
        link: optional path of a symlink to the slave device; an existing symlink is
            replaced, any other existing file is refused (``FileExistsError``).
        log_file: optional path; a frame log (header, then one record per frame),
            appended to and flushed line by line.
        log: optional callback with the ``SimBus`` log records (called from the sim
            thread; these are the simulator's own ``{t, dir, hex, family, fault}`` dicts,
            which ``framelog.from_sim`` translates).
        spin: busy-poll the port for precise timestamps (uses a whole core).
        tap: optional path of a symlink to a listen-only pty carrying a copy of every
            byte both ways (same rules as ``link``).
        pacing: ``"wire"`` (default) writes each reply when its last byte would have
            arrived at ``baud``; ``"prompt"`` writes it as soon as the request is read
            (turnaround 0, no wire time): a device behind a link that does not pace
            bytes (USB-CDC, a TCP bridge).  See ``motorbus.sim.bus``.
        echo: send every byte read from the host straight back (a half-duplex adapter
            that hears itself), before any reply.
        strict_baud: ignore what the host sends while its end of the pty is set to
            another rate than ``baud`` (counted in ``baud_mismatch_bytes``).
        device_bauds: each LA actuator hears only at its own rate (see above).
        one_at_a_time: only one device is connected at a time (see above).

    Attributes:
        bus: the ``SimBus`` (for inspection; it is driven by the sim thread).
        path: the slave device path (changes after a disconnect fault).
        dropped_bytes: output dropped because nobody drained the pty buffer.
        tap_path: the tap's slave device path ("" without a tap).
        tap_bytes: bytes copied to the tap while someone listened.
        tap_dropped_bytes: bytes a listener on the tap did not drain in time.
        error: the exception that stopped the sim thread, if any.
        echoed_bytes: bytes sent back by ``echo``.
        baud_mismatch_bytes: bytes ignored by ``strict_baud``.
    """

    def __init__(
        self,
        models: Sequence[DeviceModel],
        *,
        baud: int | None = None,
        faults: FaultConfig | None = None,
        seed: int = 0,
        link: str | os.PathLike[str] | None = None,
        log_file: str | os.PathLike[str] | None = None,
        log: Callable[[LogRecord], None] | None = None,
        spin: bool = False,
        tap: str | os.PathLike[str] | None = None,
        pacing: Pacing = "wire",
        echo: bool = False,
        strict_baud: bool = False,
        device_bauds: bool = False,
        one_at_a_time: bool = False,
    ) -> None:
        self.link = Path(link) if link is not None else None
        self.tap = Path(tap) if tap is not None else None
        #: Busy-poll the port instead of sleeping in select(): arrival timestamps and
        #: reply times then do not include this thread's own wake-up latency (100-500 us
        #: on a VM whose idle cores sleep deeply), at the cost of a whole core.  For
        #: measuring a host's timing; off by default.
        self.spin = spin
        self._log_path = Path(log_file) if log_file is not None else None
        self._log_stream: IO[str] | None = None
        self._user_log = log
        wants_log = log is not None or log_file is not None
        self.bus = SimBus(
            models,
            baud=baud if baud is not None else default_baud(models),
            faults=faults,
            seed=seed,
            log=self._write_log if wants_log else None,
            pacing=pacing,
            device_bauds=device_bauds,
        )
        #: The device connected now (``one_at_a_time``), None after the last.
        self.connected: int | None = None
        self._plugs: deque[tuple[int | None, threading.Event]] = deque()
        if one_at_a_time:
            for i in range(1, len(self.bus.models)):
                self.bus.unplug(i)
            self.connected = 0
        self.echo = bool(echo)
        self.strict_baud = bool(strict_baud)
        self.echoed_bytes = 0
        self.baud_mismatch_bytes = 0
        self.path = ""
        self.dropped_bytes = 0
        self.tap_path = ""
        self.tap_bytes = 0
        self.tap_dropped_bytes = 0
        self._tap_master: int | None = None
        self._tap_poll: select.poll | None = None
        self._tap_listening = False
        self.error: BaseException | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._wake_r: int | None = None
        self._wake_w: int | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._open = threading.Event()

    @property
    def models(self) -> tuple[DeviceModel, ...]:
        """The simulated devices."""
        return self.bus.models

    @property
    def running(self) -> bool:
        """True while the sim thread serves."""
        return self._thread is not None and self._thread.is_alive()

    def wait_open(self, timeout: float | None = None) -> bool:
        """Block until a pty is being served (e.g. after a disconnect fault ends).

        Args:
            timeout: seconds to wait at most (``None``: no limit).

        Returns:
            True if the pty is open, False on timeout.
        """
        return self._open.wait(timeout)

    def next_device(self, timeout: float = 5.0) -> int | None:
        """Unplug the connected device and plug in the next (``one_at_a_time``), powered
        up afresh; return its index (``None``: that was the last).  Returns once the sim
        thread has done it (or ``timeout`` seconds have passed)."""
        current = self.connected
        nxt = 0 if current is None else current + 1
        self.connected = nxt if nxt < len(self.bus.models) else None
        done = threading.Event()
        self._plugs.append((current, done))
        if self._wake_w is not None and self.running:
            os.write(self._wake_w, b"p")
            done.wait(timeout)
        else:
            self._apply_plugs()
        return self.connected

    def _apply_plugs(self) -> None:
        while self._plugs:
            current, done = self._plugs.popleft()
            if current is not None:
                self.bus.unplug(current)
            nxt = 0 if current is None else current + 1
            if nxt < len(self.bus.models):
                self.bus.plug(nxt, time.monotonic())
            done.set()

    def start(self) -> PtySim:
        """Open the pty, create the link, start the sim thread; return ``self``.

        Raises:
            FileExistsError: ``link`` exists and is not a symlink.
            OSError: no pty could be opened.
        """
        if self._thread is not None:
            return self
        for path in (self.link, self.tap):
            if path is not None and path.exists() and not path.is_symlink():
                raise FileExistsError(
                    errno.EEXIST, f"refusing to replace {path}: it is not a symlink", str(path)
                )
        if self._log_path is not None:
            self._log_stream = self._log_path.open("a", encoding="utf-8")
        self._open_pty()
        if self.tap is not None:
            self._open_tap(self.tap)
        if self._log_stream is not None:
            self._log_stream.write(json.dumps(self._log_header()) + "\n")
            self._log_stream.flush()
        self._wake_r, self._wake_w = os.pipe()
        self._stopping.clear()
        self.bus.epoch = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="motorbus-pty-sim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread, close the pty, remove the link, close the log.  Idempotent."""
        self._stopping.set()
        if self._wake_w is not None:
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self._close_pty()
        self._close_tap()
        for fd in (self._wake_r, self._wake_w):
            if fd is not None:
                os.close(fd)
        self._wake_r = self._wake_w = None
        if self._log_stream is not None:
            self._log_stream.close()
            self._log_stream = None

    def __enter__(self) -> PtySim:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    # -- the pty ----------------------------------------------------------------------

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.path = os.ttyname(slave)
        if self.link is not None:
            # Build the new link beside the old one and rename over it: clients never
            # see a moment without a link, nor a link to a dead pty.
            tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            tmp.symlink_to(self.path)
            os.replace(tmp, self.link)
        self._open.set()

    def _log_header(self) -> dict[str, object]:
        now = datetime.datetime.now(datetime.UTC)
        return framelog.header(
            "sim",
            started_utc=now.isoformat(timespec="microseconds").replace("+00:00", "Z"),
            families={m.family for m in self.models},
            baud=self.bus.baud,
            port=self.path,
            link=str(self.link) if self.link is not None else None,
            tap=str(self.tap) if self.tap is not None else None,
        )

    def _open_tap(self, link: Path) -> None:
        master, slave = os.openpty()
        try:
            tty.setraw(slave)  # kept by the tty while the master is open
            self.tap_path = os.ttyname(slave)
        finally:
            # Not kept open: with no slave open the master polls as hung up, which is
            # how the simulator knows that nobody listens.
            os.close(slave)
        os.set_blocking(master, False)
        self._tap_master = master
        self._tap_poll = select.poll()
        self._tap_poll.register(master, select.POLLOUT)
        tmp = link.with_name(f".{link.name}.{os.getpid()}.tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(self.tap_path)
        os.replace(tmp, link)

    def _close_tap(self) -> None:
        if self._tap_master is not None:
            with contextlib.suppress(OSError):
                os.close(self._tap_master)
        self._tap_master = None
        self._tap_poll = None
        link = self.tap
        if link is not None and link.is_symlink():
            with contextlib.suppress(OSError):
                if os.readlink(link) == self.tap_path:
                    link.unlink()

    def _copy_to_tap(self, data: bytes) -> None:
        """Copy ``data`` to the tap if someone listens; never blocks."""
        master, poller = self._tap_master, self._tap_poll
        if master is None or poller is None:
            return
        events = poller.poll(0)
        if events and events[0][1] & select.POLLHUP:
            if self._tap_listening:
                # The listener went: drop what it left unread, or the next one would
                # start with stale bytes.
                self._tap_listening = False
                with contextlib.suppress(OSError):
                    termios.tcflush(master, termios.TCOFLUSH)
            return
        self._tap_listening = True
        try:
            n = os.write(master, data)
        except BlockingIOError:
            n = 0
        except OSError as err:
            _log.debug("writing the tap failed: %s", err)
            n = 0
        self.tap_bytes += n
        self.tap_dropped_bytes += len(data) - n

    def _close_pty(self) -> None:
        self._open.clear()
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None
        if self.link is not None and self.link.is_symlink():
            with contextlib.suppress(OSError):
                if os.readlink(self.link) == self.path:
                    self.link.unlink()

    # -- the thread -------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as err:  # reported through .error; the thread must not vanish
            self.error = err
            _log.exception("pty simulator thread failed")

    def _loop(self) -> None:
        bus = self.bus
        wake_r = self._wake_r
        if wake_r is None:
            return
        while not self._stopping.is_set():
            now = time.monotonic()
            chunks = bus.due_output(now)
            if chunks:
                self._write(b"".join(chunks))
            for event in bus.link_events(now):
                if event is LinkEvent.DOWN:
                    _log.info("disconnect fault: closing %s", self.path)
                    self._close_pty()
                else:
                    self._open_pty()
                    _log.info("disconnect fault over: serving on %s", self.path)
            wakeup = bus.next_wakeup()
            if self.spin:
                timeout: float | None = 0.0
            else:
                timeout = None if wakeup is None else max(0.0, wakeup - time.monotonic())
            master = self._master
            fds = [wake_r] if master is None else [wake_r, master]
            readable, _, _ = select.select(fds, [], [], timeout)
            if wake_r in readable:
                os.read(wake_r, 64)
                self._apply_plugs()
                continue
            if master is not None and master in readable:
                try:
                    data = os.read(master, READ_SIZE)
                except BlockingIOError:
                    continue
                except OSError as err:
                    # EIO would mean nobody holds the slave; we do, so this is unexpected.
                    _log.warning("reading the pty master failed: %s", err)
                    continue
                if data:
                    now = time.monotonic()
                    if self._tap_master is not None:
                        self._copy_to_tap(data)
                    if self.echo:
                        self._write(data)
                        self.echoed_bytes += len(data)
                    if self.strict_baud and self._host_baud() not in (None, bus.baud):
                        self.baud_mismatch_bytes += len(data)
                        continue
                    if bus.device_bauds:
                        bus.set_line_rate(self._host_baud() or bus.baud)
                    bus.receive(data, now)

    def _host_baud(self) -> int | None:
        """The rate the host set on its end of the pty, or None if unknown."""
        slave = self._slave
        if slave is None:
            return None
        try:
            speed = termios.tcgetattr(slave)[5]
        except (OSError, termios.error):
            return None
        return _SPEEDS.get(speed)

    def _write(self, data: bytes) -> None:
        master = self._master
        if master is None:
            return
        if self._tap_master is not None:
            self._copy_to_tap(data)
        view = memoryview(data)
        while view:
            try:
                n = os.write(master, view)
            except BlockingIOError:
                # Nobody drains the slave: drop what does not fit, as a UART would overrun.
                self.dropped_bytes += len(view)
                return
            except OSError as err:
                _log.warning("writing the pty master failed: %s", err)
                self.dropped_bytes += len(view)
                return
            view = view[n:]

    def _write_log(self, record: LogRecord) -> None:
        if self._log_stream is not None:
            self._log_stream.write(json.dumps(framelog.from_sim(record)) + "\n")
            self._log_stream.flush()
        if self._user_log is not None:
            self._user_log(record)
