"""A served bus for tests: ``motorbus serve`` in its own process, on a free loopback
port, over simulators in their own processes (``motorbus.sim.SimProcess``); clients in
this process or in child processes that a test can kill.  Every process is ended by
its fixture, and every wait is bounded."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

from motorbus.dashboard.served import free_loopback_endpoint
from motorbus.sim import SimProcess
from tests.helpers import LOADED_HOST_MARGIN_MS
from tests.zygote import ForkedProcess, spawn_motorbus

#: Longest wait for a child process to say it is ready.
READY_TIMEOUT_S = 30.0


def free_endpoint() -> str:
    return free_loopback_endpoint()  # below the ephemeral ports: no client takes it meanwhile


class Child:
    """A child process whose stdout lines are read by a thread (waits are bounded)."""

    def __init__(self, args: list[str]) -> None:
        self.args = args
        self.proc: subprocess.Popen[str] | ForkedProcess
        if args[:3] == [sys.executable, "-m", "motorbus"]:  # forked: tests/zygote.py
            self.proc = spawn_motorbus(args[3:], new_session=True)
        else:
            self.proc = subprocess.Popen(
                args,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                start_new_session=True,
            )
        self.lines: queue.Queue[str] = queue.Queue()
        self.stderr = ""
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def expect(self, prefix: str, timeout: float = READY_TIMEOUT_S) -> str:
        """The next stdout line starting with ``prefix`` (fails after ``timeout``)."""
        while True:
            try:
                line = self.lines.get(timeout=timeout)
            except queue.Empty:
                raise AssertionError(
                    f"{self.args[3:6]} printed no {prefix!r} in {timeout:g} s; "
                    f"stderr: {self.finish()[-3000:]}"
                ) from None
            if line.startswith(prefix):
                return line

    def send(self, sig: int) -> None:
        if self.proc.poll() is None:
            os.kill(self.proc.pid, sig)

    def finish(self, sig: int = signal.SIGTERM) -> str:
        """End the process (``sig``, then SIGKILL) and return its stderr."""
        if self.proc.poll() is None:
            with_cont = sig != signal.SIGKILL
            os.kill(self.proc.pid, sig)
            if with_cont:
                os.kill(self.proc.pid, signal.SIGCONT)
        try:
            _, err = self.proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, err = self.proc.communicate()
        self.stderr = err or self.stderr
        return self.stderr


def serve(port: str, baud: int, devices: str, endpoint: str, *extra: str) -> Child:
    """``motorbus serve --port ...`` started; waits for its "serving" line."""
    child = Child(
        [
            sys.executable,
            "-m",
            "motorbus",
            "serve",
            "--port",
            port,
            "--baud",
            str(baud),
            "--devices",
            devices,
            "--listen",
            endpoint,
            "--host-margin-ms",
            # A loaded CI machine (a scan's status of la:1 timed out at 50 ms with eight
            # workers): no false timeouts.  The tests that wait for one ask an ID that
            # is not simulated, and wait for it as long as it takes.
            str(LOADED_HOST_MARGIN_MS),
            *extra,
        ]
    )
    child.expect("serving")
    return child


def client(endpoint: str, body: str) -> Child:
    """A client in its own process: ``body`` runs inside ``async with
    motorbus.connect(endpoint) as site:`` with ``bus = site.bus()``; it prints what
    the test waits for and then waits to be ended."""
    code = textwrap.dedent(
        """
        import asyncio, sys, motorbus
        from motorbus import InspireLA, ProjectStepper, QuadStepper
        from motorbus.protocol import la

        async def main():
            async with motorbus.connect(sys.argv[1], name="child") as site:
                bus = site.bus()
        {body}
                print("ready", flush=True)
                await asyncio.sleep(120)

        asyncio.run(main())
        """
    ).format(body=textwrap.indent(textwrap.dedent(body), " " * 8))
    return Child([sys.executable, "-c", code, endpoint])


@pytest.fixture
def la_sim(tmp_path: Path) -> Iterator[SimProcess]:
    with SimProcess(["la:1-2"], baud=921600, log_file=tmp_path / "sim.jsonl") as sim:
        yield sim


@pytest.fixture
def endpoint() -> str:
    return free_endpoint()


@pytest.fixture
def la_server(la_sim: SimProcess, endpoint: str) -> Iterator[Child]:
    server = serve(la_sim.path, 921600, "la:1-2", endpoint, "--liveness", "0.5")
    try:
        yield server
    finally:
        server.finish()


@pytest.fixture
def stepper_server() -> Iterator[str]:
    """A served bus of a project stepper and a quad stepper (9600 bit/s): its endpoint."""
    endpoint = free_endpoint()
    with SimProcess(["project-stepper", "quad-stepper"], baud=9600) as sim:
        server = serve(sim.path, 9600, "project-stepper,quad-stepper", endpoint)
        try:
            yield endpoint
        finally:
            server.finish()
