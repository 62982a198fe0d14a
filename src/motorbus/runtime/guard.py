"""The guard: a second process that sends the safe action when the program cannot.

A program that is killed (SIGKILL, the OOM killer, a crash of the interpreter) runs
none of its ``finally`` blocks: whatever it last sent keeps the devices moving.  The
guard is an opt-in helper process (``motorbus.run(main(), guard=True)``, ``--guard``
on the CLI commands that move things, ``guard = true`` in a bus file) that:

* watches the program through a pidfd (Linux 5.3+; elsewhere starting it raises
  :class:`~motorbus.errors.GuardError`), so it learns of the death at once, however
  it happens;
* is told over a pipe, on every change, which devices each open bus has leased and
  their safe frames (``bus.add_lease_listener``), with the port's URL, baud rate and
  options; a bus that closes cleanly (its leases ended with their safe action) is
  forgotten;
* when the program dies with leases still held, opens those ports and writes every
  leased device's safe frames, each once the line is quiet (a device answering the
  program's last request, or the guard's previous frame, would not hear a frame written
  meanwhile: the buses are half duplex; see :func:`wait_for_quiet`), then exits.  A
  program that ends cleanly tells it so and it exits without touching anything.

It runs in its own session, so a Ctrl-C to the terminal's process group does not
reach it, and it ignores SIGINT, SIGHUP and SIGTERM (it exits by itself once the
program has ended; SIGKILL ends it).  What no software can cover: a host crash
or kernel panic, a power cut to the host, a cut cable or a dead USB adapter - the
guard dies with the host or cannot reach the device.  Use the hardware e-stop for
those.

The pipe carries JSON lines (``{"op": "port", ...}``, ``{"op": "closed", ...}``,
``{"op": "clean_exit"}``); :class:`GuardState` is the pure part that reads them.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import IO, Any

from motorbus.errors import GuardError, LocalProtocolError
from motorbus.protocol.base import wire_time

__all__ = [
    "FRAME_SPACING_S",
    "GAP_AFTER_REPLY_S",
    "Guard",
    "GuardDevice",
    "GuardPort",
    "GuardState",
    "active_guard",
    "guarded",
    "start_guard",
    "stop_guard",
    "wait_for_quiet",
]

log = logging.getLogger("motorbus.guard")

#: Pause between two safe frames on one port, after the first is drained to the line.
FRAME_SPACING_S = 0.001
#: Once a reply was heard, how long the line must stay silent (besides the next frame's
#: own wire time) before the guard writes: the reply has ended.
GAP_AFTER_REPLY_S = 0.002
#: Longest wait for a quiet line before one frame: a line that never falls silent gets
#: the frame anyway.
QUIET_LIMIT_S = 0.5
#: A network port (``socket://``, ``rfc2217://``: ser2net) closes only once the last
#: frame's answer was heard, or after this long: its server may still hold the frame when
#: the guard is done writing, and on a loaded machine a close within the device's
#: turnaround overtook it (the device never got the last pause).
NETWORK_CLOSE_WAIT_S = QUIET_LIMIT_S
#: How often the guard looks at the line while it waits for quiet.
QUIET_POLL_S = 0.0002
#: The host's share of a device's answer time: a USB adapter holds received bytes up to
#: 1 ms (docs/platform.md).  Not the bus's ``host_margin``, which a loaded test machine
#: raises to tens of milliseconds: every kill would wait that long before its first frame.
HOST_SHARE_S = 0.002
#: A reply length the program assumes when it tells the guard how long a device may take
#: to answer (longer than every status and acknowledgement of the three manuals; the
#: stepper's 226-byte project dump is the exception).
REPLY_BYTES = 24
#: Longest wait for a new guard process to say it watches the program.
READY_TIMEOUT_S = 20.0
#: Longest wait for the guard to exit after a clean exit was announced.
EXIT_TIMEOUT_S = 2.0
#: What the guard prints on stdout once it watches the program.
READY_LINE = "motorbus-guard ready"
#: Longest a JSON line on the pipe may be (a bus with 254 leased devices fits easily).
MAX_LINE = 1 << 20
#: Environment variable: a file the guard writes what it did to, as JSON (diagnostics;
#: times are ``time.monotonic()``, comparable between processes on Linux).
REPORT_ENV = "MOTORBUS_GUARD_REPORT"
#: How long the guard waits for a port to accept a write before giving up on it.
WRITE_TIMEOUT_S = 1.0


# -- the pure part: what the guard knows -------------------------------------------------


@dataclass(frozen=True)
class GuardDevice:
    """One leased device: its key, its owner and the frames of its safe action."""

    key: str
    owner: str
    safe_frames: tuple[bytes, ...]


@dataclass(frozen=True)
class GuardPort:
    """One open bus as the guard sees it: how to open its port and what to send."""

    url: str
    baud: int
    options: Mapping[str, Any] = field(default_factory=dict)
    devices: tuple[GuardDevice, ...] = ()

    @property
    def frames(self) -> tuple[bytes, ...]:
        """Every safe frame to send on this port, device by device."""
        return tuple(f for d in self.devices for f in d.safe_frames)


def port_message(bus_id: str, port: GuardPort) -> dict[str, Any]:
    """The pipe message that replaces what the guard knows of bus ``bus_id``."""
    return {
        "op": "port",
        "bus": bus_id,
        "url": port.url,
        "baud": port.baud,
        "options": dict(port.options),
        "devices": [
            {"key": d.key, "owner": d.owner, "safe": [f.hex() for f in d.safe_frames]}
            for d in port.devices
        ],
    }


def _field(message: Mapping[str, Any], key: str, kind: type | tuple[type, ...]) -> Any:
    value = message.get(key)
    if not isinstance(value, kind) or (isinstance(value, bool) and kind is int):
        raise LocalProtocolError(
            f"guard message: {key}={value!r} is not allowed: expected {kind}", field=key
        )
    return value


def _device(raw: object) -> GuardDevice:
    if not isinstance(raw, dict):
        raise LocalProtocolError(f"guard message: device {raw!r} is not an object", field="devices")
    frames = _field(raw, "safe", list)
    try:
        safe = tuple(bytes.fromhex(h) for h in frames)
    except (TypeError, ValueError) as err:
        raise LocalProtocolError(
            f"guard message: safe={frames!r} is not a list of hex frames", field="safe"
        ) from err
    return GuardDevice(str(_field(raw, "key", str)), str(_field(raw, "owner", str)), safe)


class GuardState:
    """What the guard knows: every open bus's port and leased devices (pure)."""

    def __init__(self) -> None:
        self.ports: dict[str, GuardPort] = {}
        self.clean_exit = False

    def apply(self, message: Mapping[str, Any]) -> None:
        """Apply one pipe message.

        Raises:
            LocalProtocolError: an unknown ``op`` or a malformed field (named).
        """
        op = message.get("op")
        if op == "clean_exit":
            self.clean_exit = True
        elif op == "closed":
            self.ports.pop(str(_field(message, "bus", str)), None)
        elif op == "port":
            url = _field(message, "url", str)
            if not url or "\0" in url:
                raise LocalProtocolError(f"guard message: url={url!r} is not a port", field="url")
            baud = _field(message, "baud", int)
            if baud <= 0:
                raise LocalProtocolError(f"guard message: baud={baud} must be > 0", field="baud")
            devices = tuple(_device(d) for d in _field(message, "devices", list))
            options = _field(message, "options", dict)
            quiet = options.get("quiet_s", 0.0)
            if (
                not isinstance(quiet, int | float)
                or isinstance(quiet, bool)
                or not (0 <= quiet <= QUIET_LIMIT_S)
            ):
                raise LocalProtocolError(
                    f"guard message: quiet_s={quiet!r} is not allowed: 0..{QUIET_LIMIT_S} s",
                    field="quiet_s",
                )
            self.ports[_field(message, "bus", str)] = GuardPort(url, baud, options, devices)
        else:
            raise LocalProtocolError(
                f"guard message: op={op!r} is not allowed: choose port, closed or clean_exit",
                field="op",
            )

    def plan(self) -> list[GuardPort]:
        """The ports to open after a death, each with something to send."""
        return [p for p in self.ports.values() if p.frames]


# -- the guard process ---------------------------------------------------------------------


@dataclass
class PortResult:
    """What the guard did on one port (times are ``time.monotonic()``)."""

    url: str
    frames: int = 0
    devices: int = 0
    opened: float | None = None
    last_write: float | None = None
    error: str | None = None


def wait_for_quiet(
    ser: Any,
    quiet: float,
    gap: float,
    *,
    limit: float = QUIET_LIMIT_S,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> int:
    """Read and drop what the line carries until it is quiet; return the bytes heard.

    Quiet: nothing heard for ``quiet`` seconds (a device that was asked something
    answers within that), or, once bytes were heard, nothing more for ``gap`` seconds
    (the reply has ended).  At most ``limit`` seconds.  ``ser.read`` must not block
    (the port opens with ``timeout=0``).
    """
    start = last = clock()
    heard = 0
    while True:
        data = ser.read(4096)
        now = clock()
        if data:
            heard += len(data)
            last = now
        if now - last >= (gap if heard else quiet) or now - start >= limit:
            return heard
        sleep(QUIET_POLL_S)


def send_safe_frames(
    port: GuardPort,
    *,
    spacing: float = FRAME_SPACING_S,
    opener: Callable[[GuardPort], Any] | None = None,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> PortResult:
    """Open ``port`` and write its safe frames, ``spacing`` apart after each drains.

    With ``port.options["quiet_s"]`` (the program sends it: its devices' longest
    turnaround and reply), each frame waits for a quiet line first
    (:func:`wait_for_quiet`): before the first, a device may still be answering the
    program's last request; before the next, the device answers the guard's frame;
    and before the port closes, the device answers the last one.
    The frame's own wire time is added, since a pty (or a USB adapter) takes the bytes
    at once but a half-duplex line carries them for that long.
    """
    result = PortResult(port.url, devices=len(port.devices))
    quiet = float(port.options.get("quiet_s", 0.0))
    try:
        ser = (opener or _open_serial)(port)
    except Exception as err:  # any failure is reported; the other ports go on
        result.error = f"cannot open {port.url}: {err}"
        return result
    result.opened = clock()
    try:
        for n, frame in enumerate(port.frames):
            if n:
                sleep(spacing)
            if quiet:
                own = wire_time(len(frame), port.baud)
                wait_for_quiet(ser, quiet + own, GAP_AFTER_REPLY_S + own, clock=clock, sleep=sleep)
            ser.write(frame)
            ser.flush()  # tcdrain: the frame is on the line before the pause starts
            result.frames += 1
            result.last_write = clock()
        if quiet and port.frames:
            # Close only once the last frame's answer is over: a ``socket://`` port
            # (ser2net) cannot drain to the line, and its close must not overtake the
            # frame on its way to the device: there, wait to hear the answer.
            own = wire_time(len(port.frames[-1]), port.baud)
            # (A URL is a network port: transport.serial.is_device_path's rule; that
            # module would cost the guard its import.)
            silent = NETWORK_CLOSE_WAIT_S if "://" in port.url else quiet + own
            wait_for_quiet(ser, silent, GAP_AFTER_REPLY_S + own, clock=clock, sleep=sleep)
    except Exception as err:
        result.error = f"writing to {port.url} failed after {result.frames} frames: {err}"
    finally:
        with contextlib.suppress(Exception):
            ser.close()
    return result


def _open_serial(port: GuardPort) -> Any:
    import serial  # the guard process only; pyserial is a motorbus dependency

    url = port.url
    if url.startswith("usb:"):
        # An adapter named by its USB identity: where it is now (it may have come back
        # under another name since the program opened it).  Imported only then: the
        # transport package costs the guard tens of ms before its first frame.
        from motorbus.transport.usb import resolve_port

        url = resolve_port(url)
    ser = serial.serial_for_url(
        url,
        baudrate=port.baud,
        timeout=0,
        write_timeout=WRITE_TIMEOUT_S,
        do_not_open=True,
    )
    if port.options.get("rs485"):
        import serial.rs485

        ser.rs485_mode = serial.rs485.RS485Settings()
    ser.open()
    return ser


def act(state: GuardState, *, spacing: float = FRAME_SPACING_S) -> list[PortResult]:
    """Send every planned port's safe frames, the ports in parallel."""
    plan = state.plan()
    results: list[PortResult] = [PortResult(p.url) for p in plan]

    def one(n: int, port: GuardPort) -> None:
        results[n] = send_safe_frames(port, spacing=spacing)

    threads = [threading.Thread(target=one, args=(n, p)) for n, p in enumerate(plan)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


def _read_lines(fd: int, buf: bytearray, state: GuardState, *, until_eof: bool) -> bool:
    """Read what the pipe holds into ``state``; return False at end of file."""
    while True:
        try:
            data = os.read(fd, 65536)
        except BlockingIOError:
            return True
        if not data:
            return False
        buf += data
        while b"\n" in buf:
            line, _, rest = bytes(buf).partition(b"\n")
            buf[:] = rest
            if line.strip():
                try:
                    state.apply(json.loads(line))
                except (ValueError, LocalProtocolError) as err:
                    print(f"motorbus guard: ignored a bad message: {err}", file=sys.stderr)
        if len(buf) > MAX_LINE:
            buf.clear()
        if not until_eof:
            return True


def serve(pidfd: int, pid: int, *, report: str | None = None, stdin: int = 0) -> int:
    """Watch ``pidfd``; act if the program dies with leases held.  Returns the exit code."""
    # It ends by itself once the program has ended; a signal meant for the program
    # (a terminal's Ctrl-C, systemd's SIGTERM to the whole unit) must not end it first.
    for sig in (signal.SIGINT, signal.SIGHUP, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    os.set_blocking(stdin, False)
    with contextlib.suppress(ImportError):
        import serial  # noqa: F401 - now, not in the milliseconds after a death
    state = GuardState()
    buf = bytearray()
    poller = select.poll()
    poller.register(pidfd, select.POLLIN)
    poller.register(stdin, select.POLLIN)
    print(READY_LINE, flush=True)
    dead = False
    while not dead:
        for fd, _ in poller.poll():
            if fd == stdin and not _read_lines(stdin, buf, state, until_eof=False):
                poller.unregister(stdin)  # the program closed the pipe (or died)
            elif fd == pidfd:
                dead = True
        if state.clean_exit:
            return 0
    died = time.monotonic()
    # Updates written just before the death are still in the pipe: read them all.
    with contextlib.suppress(OSError):
        _read_lines(stdin, buf, state, until_eof=True)
    if state.clean_exit:
        return 0
    results = act(state)
    _report(pid, died, results, report)
    return 1 if any(r.error for r in results) else 0


def _report(pid: int, died: float, results: Sequence[PortResult], path: str | None) -> None:
    for r in results:
        if r.error:
            print(f"motorbus guard: program {pid}: {r.error}", file=sys.stderr)
        elif r.last_write is not None:
            ms = (r.last_write - died) * 1e3
            print(
                f"motorbus guard: program {pid} ended without closing its buses: sent the "
                f"safe action to {r.devices} device(s) on {r.url} ({r.frames} frames, the "
                f"last {ms:.1f} ms after it ended)",
                file=sys.stderr,
            )
    if path:
        doc = {
            "pid": pid,
            "died": died,
            "ports": [r.__dict__ for r in results],
        }
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(doc, fh)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m motorbus.runtime.guard --pidfd N --pid P``: run the guard (see the module)."""
    parser = argparse.ArgumentParser(prog="python -m motorbus.runtime.guard", description=__doc__)
    parser.add_argument("--pidfd", type=int, help="an inherited pidfd of the program")
    parser.add_argument("--pid", type=int, required=True, help="the program's process ID")
    parser.add_argument("--report", help="write what was done as JSON to this file")
    args = parser.parse_args(argv)
    try:
        pidfd = args.pidfd if args.pidfd is not None else os.pidfd_open(args.pid)
    except ProcessLookupError:
        print(f"motorbus guard: program {args.pid} is gone already", file=sys.stderr)
        return 1
    return serve(pidfd, args.pid, report=args.report)


# -- the program's side ---------------------------------------------------------------------


def _port_of(bus: Any) -> tuple[str, int, dict[str, Any]] | None:
    """How the guard would open ``bus``'s port, or None (an in-memory link); its
    ``quiet_s``: how long a device of the bus may take to answer a request
    (``bus.answer_window`` for a reply of :data:`REPLY_BYTES`, plus
    :data:`HOST_SHARE_S`)."""
    transport = getattr(bus, "transport", None)
    url = getattr(transport, "url", None)
    if not isinstance(url, str):
        return None
    baud = int(bus.baudrate)
    options: dict[str, Any] = {"rs485": bool(getattr(transport, "rs485", False))}
    window = getattr(bus, "answer_window", None)
    if window is not None:
        options["quiet_s"] = min(window(REPLY_BYTES) + HOST_SHARE_S, QUIET_LIMIT_S)
    return url, baud, options


def _devices(snapshot: Sequence[Any]) -> tuple[GuardDevice, ...]:
    return tuple(
        GuardDevice(str(info.key), str(info.owner), tuple(bytes(f) for f in info.safe_frames))
        for info in snapshot
        if info.safe_frames
    )


class Guard:
    """The program's handle on its guard process (``start_guard`` makes one).

    Raises (``start``):
        GuardError: no pidfds on this system, or the guard did not start.
    """

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self.proc = proc
        self.ports: dict[str, GuardPort] = {}
        self._listeners: dict[str, tuple[Any, Callable[[Any], None]]] = {}
        self._lost = False

    @classmethod
    def start(cls, *, report: str | None = None) -> Guard:
        """Spawn ``python -m motorbus.runtime.guard`` watching this process; wait until it
        watches."""
        pidfd_open = getattr(os, "pidfd_open", None)
        if pidfd_open is None:
            raise GuardError(
                f"the guard needs Linux pidfds (os.pidfd_open), which {sys.platform} lacks; "
                "run without the guard, and rely on the hardware e-stop"
            )
        try:
            pidfd = pidfd_open(os.getpid())
        except OSError as err:
            raise GuardError(f"the guard needs a pidfd (Linux 5.3+): {err}") from err
        cmd = [sys.executable, "-m", "motorbus.runtime.guard", "--pid", str(os.getpid())]
        cmd += ["--pidfd", str(pidfd)] + (["--report", report] if report else [])
        try:
            proc = subprocess.Popen(
                cmd,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                pass_fds=(pidfd,),
                start_new_session=True,  # a Ctrl-C to the program's group is not for it
            )
        except OSError as err:
            raise GuardError(f"the guard process did not start: {err}") from err
        finally:
            os.close(pidfd)
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], READY_TIMEOUT_S)
        line = proc.stdout.readline().decode(errors="replace").strip() if ready else ""
        if line != READY_LINE:
            proc.kill()
            proc.wait()
            raise GuardError(f"the guard process did not start (said {line!r})")
        return cls(proc)

    @property
    def alive(self) -> bool:
        """True while the guard process runs and the pipe to it works."""
        return not self._lost and self.proc.poll() is None

    def _send(self, message: Mapping[str, Any]) -> None:
        if self._lost:
            return
        stdin: IO[bytes] | None = self.proc.stdin
        try:
            assert stdin is not None
            stdin.write(json.dumps(message).encode() + b"\n")
            stdin.flush()
        except (OSError, ValueError) as err:
            self._lost = True
            log.error(
                "the guard process is gone (%s): nothing will stop the devices if "
                "this program is killed",
                err,
            )

    def set_port(self, bus_id: str, port: GuardPort) -> None:
        """Tell the guard what bus ``bus_id`` has open and leased (replaces the last)."""
        self.ports[bus_id] = port
        self._send(port_message(bus_id, port))

    def forget(self, bus_id: str) -> None:
        """Bus ``bus_id`` closed cleanly: nothing of it is left to stop."""
        self.ports.pop(bus_id, None)
        self._send({"op": "closed", "bus": bus_id})

    def watch(self, bus: Any) -> None:
        """Follow ``bus``'s leases (``bus.add_lease_listener``) until ``unwatch``."""
        where = _port_of(bus)
        if where is None:
            return  # an in-memory link: there is no port a guard could open
        bus_id = f"{getattr(bus, 'name', 'bus')}@{id(bus):x}"
        url, baud, options = where

        def on_change(snapshot: Sequence[Any]) -> None:
            # Runs inside the bus's lease change: it must never break the motion.
            try:
                self.set_port(bus_id, GuardPort(url, baud, options, _devices(snapshot)))
            except Exception as err:
                log.error("bus %s: the guard could not be told of a lease change: %s", bus_id, err)

        add = getattr(bus, "add_lease_listener", None)
        if add is None:
            log.warning("bus %s has no leases: the guard cannot know what to stop", bus_id)
        else:
            add(on_change)
        self._listeners[bus_id] = (bus, on_change)
        on_change(tuple(getattr(bus, "leases", ())))

    def unwatch(self, bus: Any) -> None:
        """``bus`` closed: stop following it and tell the guard."""
        for bus_id, (watched, listener) in list(self._listeners.items()):
            if watched is bus:
                remove = getattr(bus, "remove_lease_listener", None)
                if remove is not None:
                    remove(listener)
                del self._listeners[bus_id]
                self.forget(bus_id)

    def close(self) -> None:
        """The program ends cleanly: let the guard exit without sending anything.

        If a bus still has leased devices (it was not closed), the guard is left
        running: it sends their safe action when this process has exited.
        """
        if any(p.frames for p in self.ports.values()):
            log.warning("a bus is still open with leased devices: the guard stays to stop them")
            return
        self._send({"op": "clean_exit"})
        with contextlib.suppress(OSError, ValueError):
            if self.proc.stdin is not None:
                self.proc.stdin.close()
        try:
            self.proc.wait(EXIT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


_active: Guard | None = None


def active_guard() -> Guard | None:
    """The guard this process started, if any."""
    return _active


def start_guard(*, report: str | None = None) -> Guard:
    """Start the guard of this process (once; later calls return the same one).

    Every bus opened from now on is followed (``motorbus.runtime.shutdown`` calls
    ``bus_opened``/``bus_closed``); buses already open are not.

    Raises:
        GuardError: see :class:`Guard`.
    """
    global _active
    if _active is None or not _active.alive:
        _active = Guard.start(report=report or os.environ.get(REPORT_ENV) or None)
    return _active


def stop_guard() -> None:
    """The program ends cleanly: let the guard go (see ``Guard.close``)."""
    global _active
    guard, _active = _active, None
    if guard is not None:
        guard.close()


@contextlib.contextmanager
def guarded(enabled: bool = True) -> Iterator[Guard | None]:
    """``with guarded():`` start the guard, and let it go when the block ends in Python.

    A block that ends by an exception (Ctrl-C included) has closed its buses on the
    way out, so this is a clean end too; only a death that runs no Python (SIGKILL,
    the OOM killer, a crash) leaves the guard to act.
    """
    if not enabled:
        yield None
        return
    guard = start_guard()
    try:
        yield guard
    finally:
        stop_guard()


def bus_opened(bus: Any) -> None:
    """Called by ``motorbus.runtime.shutdown.register_bus``: follow ``bus`` if a guard runs."""
    if _active is not None:
        _active.watch(bus)


def bus_closed(bus: Any) -> None:
    """Called by ``motorbus.runtime.shutdown.unregister_bus``."""
    if _active is not None:
        _active.unwatch(bus)


if __name__ == "__main__":
    sys.exit(main())
