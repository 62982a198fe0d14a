"""Run ``motorbus sim`` in a child process, as a real device would be: outside ours.

A simulator in its own process does not share our GIL, so its reply timing does not
depend on what our event loop is doing - which is what the demo, the benchmarks and
the end-to-end tests need.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

from motorbus.protocol import framelog
from motorbus.sim.bus import Pacing, check_pacing
from motorbus.sim.faults import FaultConfig
from motorbus.sim.spec import parse_device_specs

__all__ = ["SimProcess"]

#: Longest wait for the child to print its device path.
START_TIMEOUT_S = 20.0


class SimProcess:
    """``with SimProcess(["la:1-15"], baud=921600) as sim: open(sim.path)...``.

    Args:
        devices: device specs as for ``motorbus sim`` ("la:1-15", "project-stepper"...).
        baud: emulated baud rate (default: the simulator's choice per device kind).
        faults: a ``--faults`` spec string, e.g. ``"garbage=0.01,late=0.01:0.05"``.
        seed: seed of turnarounds and faults.
        log_file: record every frame both ways as JSON lines to this path.
        link: create this symlink to the pty.
        spin: busy-poll the port for precise timestamps (``motorbus sim --spin``).
        tap: serve a listen-only copy of the traffic on a pty linked here (``--tap``).
        pacing: ``"wire"`` (default) emulates wire time; ``"prompt"`` answers at once
            (``motorbus sim --pacing prompt``; see ``motorbus.sim.bus``).
        device_bauds: each LA actuator hears only at its own rate (``--device-bauds``).
        one_at_a_time: only the first device is connected; :meth:`next_device` plugs in
            the next (``--one-at-a-time``).

    Raises:
        LocalProtocolError: at construction, before any process starts: a device spec
            ``motorbus sim`` would refuse (an unknown kind - the message names the spec,
            the kind and the allowed kinds -, a bad ID or option), a bad ``faults``
            spec, or ``pacing`` not ``"wire"`` or ``"prompt"``.
    """

    def __init__(
        self,
        devices: Sequence[str],
        *,
        baud: int | None = None,
        faults: str | None = None,
        seed: int = 0,
        log_file: str | os.PathLike[str] | None = None,
        link: str | os.PathLike[str] | None = None,
        spin: bool = False,
        tap: str | os.PathLike[str] | None = None,
        pacing: Pacing = "wire",
        device_bauds: bool = False,
        one_at_a_time: bool = False,
    ) -> None:
        self.pacing: Pacing = check_pacing(pacing)
        # Checked here, as the child would check them: a bad spec is the caller's error,
        # named now, not a child that "did not start".
        parse_device_specs(devices)
        FaultConfig.parse(faults or "")
        self.args = [sys.executable, "-m", "motorbus", "sim"]
        self.args += ["--device-bauds"] if device_bauds else []
        self.args += ["--one-at-a-time"] if one_at_a_time else []
        if spin:
            self.args.append("--spin")
        if self.pacing != "wire":
            self.args += ["--pacing", self.pacing]
        if baud is not None:
            self.args += ["--baud", str(baud)]
        if faults:
            self.args += ["--faults", faults]
        self.args += ["--seed", str(seed)]
        if log_file is not None:
            self.args += ["--log", os.fspath(log_file)]
        if link is not None:
            self.args += ["--link", os.fspath(link)]
        if tap is not None:
            self.args += ["--tap", os.fspath(tap)]
        self.args += list(devices)
        self.log_file = Path(log_file) if log_file is not None else None
        self.tap = Path(tap) if tap is not None else None
        self.proc: subprocess.Popen[str] | None = None
        self.path = ""
        self.summary = ""

    def start(self) -> SimProcess:
        """Start the child and wait for its device path."""
        self.proc = subprocess.Popen(
            self.args,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,  # a Ctrl-C to our group must not kill the device first
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline().strip()
        if not line:
            err = self.proc.stderr.read() if self.proc.stderr else ""
            self.proc.wait(START_TIMEOUT_S)
            raise RuntimeError(f"motorbus sim did not start: {err.strip()}")
        self.path = line.split()[0]
        return self

    def next_device(self, timeout: float = START_TIMEOUT_S) -> str:
        """``one_at_a_time``: unplug the connected device, plug in the next; return the
        simulator's line saying which (``connected device #N``) once it has done it."""
        assert self.proc is not None and self.proc.stderr is not None
        self.proc.send_signal(signal.SIGUSR1)
        fd = self.proc.stderr.fileno()
        line = b""
        while select.select([fd], [], [], timeout)[0]:
            byte = os.read(fd, 1)
            if not byte or byte == b"\n":
                if b"connected device" in line:
                    return line.decode().strip()
                if not byte:
                    break
                line = b""
            else:
                line += byte
        raise RuntimeError(f"motorbus sim did not connect the next device: {line!r}")

    def stop(self) -> str:
        """Interrupt the child (SIGINT) and return its one-line summary."""
        if self.proc is None:
            return self.summary
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            out, _ = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        self.summary = out.strip()
        self.proc = None
        return self.summary

    def log_records(self) -> list[dict[str, Any]]:
        """The frame-log records the simulator wrote so far, headers left out.

        ``log_file`` must have been given.  Each is a record of docs/frame-log.md:
        ``r["direction"] == "request"`` for what the simulator received (frames and
        garbage), ``"reply"`` for what it sent.  A line still being written is skipped.
        """
        if self.log_file is None or not self.log_file.exists():
            return []
        # One read to the end, then the whole lines: iterating the file read on past
        # an end of file met mid-record, and took the rest of the record, written
        # meanwhile, for a line of its own.
        with self.log_file.open(encoding="utf-8") as fh:
            pieces = fh.read().split("\n")
        lines = [piece + "\n" for piece in pieces[:-1]]  # the last one is unfinished
        return framelog.read_frame_log(lines, str(self.log_file)).records

    def __enter__(self) -> SimProcess:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
