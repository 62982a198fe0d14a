"""The dashboard on a served bus: it watches and drives buses a ``motorbus serve`` owns.

``motorbus dashboard --connect ENDPOINT`` attaches to a running server;
``motorbus dashboard --port ...`` (or a bus file) starts one of its own
(:class:`ServeChild`) and attaches to it.  Either way the dashboard never runs on the
bus's event loop: the bus, its spacing, deadlines and leases live in the server's
process, and a burst of viewers costs the dashboard's process, not the bus's.

What the page shows comes through the served bus (``motorbus.connect``; this module
only needs its members, :class:`ServedBusLike`): the statuses the poller reads (at
``Priority.BACKGROUND``: every other request on the server's bus goes first), the
server's counters (``fetch_stats``), who holds which device (``leases``) and the bus's
events.  The frames the dashboard itself sends and the replies it gets feed the state
and the recorder with this process's times, as the bus's observer does for a bus of
its own.

Controls go through the server too: e-stop at ``Priority.EMERGENCY`` (ahead of every
status query and every other client's normal request), the others at ``HIGH``.  A move
or a "work" belongs to the dashboard's client lease on the server, so the served-bus
lease rules apply: a device another client holds is refused, naming the holder, and
nothing is sent.  When the dashboard ends, however it ends, the server ends that lease
with the bus's safe action (the deadman), after the dashboard's own safe stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import signal
import socket
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, cast

from motorbus.bus.bus import Bus, Priority
from motorbus.bus.leases import PROGRAM, LeaseInfo
from motorbus.dashboard.runtime import BusSetup, Dashboard
from motorbus.errors import MotorbusError, ServeChildError
from motorbus.protocol import la
from motorbus.protocol.base import Command

__all__ = [
    "READY_TIMEOUT_S",
    "SERVE_STOP_TIMEOUT_S",
    "TELEMETRY_PERIOD_S",
    "ServeChild",
    "ServeChildError",
    "ServedBusLike",
    "ServedDashboard",
    "SiteLike",
    "Watch",
    "free_loopback_endpoint",
    "served_name",
    "watch_site",
]

log = logging.getLogger("motorbus.dashboard")

#: Seconds between two reads of a served bus's counters and leases.
TELEMETRY_PERIOD_S = 0.5
#: Longest wait for a ``motorbus serve`` child to print its ready line.
READY_TIMEOUT_S = 30.0
#: Longest wait for the child to end after SIGTERM (its safe ends) before SIGKILL.
SERVE_STOP_TIMEOUT_S = 10.0
#: How the dashboard's own lease shows on its page.
SELF_OWNER = "this dashboard"


class ServedBusLike(Protocol):
    """What the dashboard uses of a served bus (``motorbus.serve.ServedBus``) beyond the
    members it shares with ``Bus``."""

    name: str

    @property
    def state(self) -> str: ...

    @property
    def leases(self) -> tuple[LeaseInfo, ...]: ...

    async def fetch_stats(self) -> dict[str, Any]: ...


class ServedDashboard(Dashboard):
    """A :class:`Dashboard` whose buses are served buses of the server at ``endpoint``.

    Args:
        setups: the served buses (``site.bus(name)``, typed as ``Bus``) and their devices.
        endpoint: the server's Zenoh endpoint (shown on the page).
        period, control, window: as :class:`Dashboard`.
    """

    def __init__(
        self,
        setups: Iterable[BusSetup],
        *,
        endpoint: str,
        period: float = 0.1,
        control: bool = False,
        window: tuple[int, int] = (la.POSITION_MIN, la.POSITION_MAX),
    ) -> None:
        super().__init__(setups, period=period, control=control, window=window)
        self.endpoint = endpoint
        self._served_stats: dict[str, dict[str, Any]] = {name: {} for name in self.setups}
        for name in self.setups:
            self.state.set_served(name, endpoint)

    def _served(self, name: str) -> ServedBusLike:
        return cast(ServedBusLike, self.setups[name].bus)

    def _attach(self, name: str, s: BusSetup) -> None:
        self.state.set_state(name, self._served(name).state)
        loop = asyncio.get_running_loop()
        self._tasks.append(
            loop.create_task(self._telemetry(name), name=f"dashboard telemetry {name}")
        )

    def _detach(self) -> None:
        """Nothing to undo: the server ends the dashboard's lease when it leaves."""

    async def _request(
        self,
        name: str,
        cmd: Command[object],
        priority: Priority,
        retries: int | None = None,
    ) -> Any:
        bus = self.setups[name].bus
        observer = self._observers.get(name)
        written = bus.timer.now()
        if observer is not None:
            observer.on_write(cmd, written)
        value = await bus.request(cmd, priority=priority, retries=retries)
        if observer is not None:
            observer.on_reply(cmd, value, written, bus.timer.now())
        return value

    def _is_open(self, name: str) -> bool:
        return self._served(name).state == "open"

    def _stats(self, name: str) -> dict[str, Any]:
        return self._served_stats[name]

    def _port(self, name: str) -> str:
        return f"{self.endpoint} (served bus {self.setups[name].bus.name})"

    async def _telemetry(self, name: str) -> None:
        """The server's counters (and frames/s from them) and the leases, every
        :data:`TELEMETRY_PERIOD_S`."""
        bus = self._served(name)
        loop = asyncio.get_running_loop()
        last: tuple[float, int] | None = None
        while True:
            try:
                stats = await bus.fetch_stats()
                infos = await asyncio.to_thread(lambda: bus.leases)
            except MotorbusError as err:
                log.debug("dashboard: counters of served bus %s: %s", name, err)
                last = None
            else:
                now = loop.time()
                self._served_stats[name] = stats
                requests = int(stats.get("requests", 0))
                if last is not None and now > last[0]:
                    self.state.set_rate(name, (requests - last[1]) / (now - last[0]))
                last = (now, requests)
                self.state.set_leases(
                    name, [(i.key, SELF_OWNER if i.owner == PROGRAM else i.owner) for i in infos]
                )
            await asyncio.sleep(TELEMETRY_PERIOD_S)


def _die_with_parent() -> None:  # pragma: no cover - runs in the child, before exec
    """Linux: the child gets SIGTERM (its safe ends) if the dashboard dies, SIGKILL
    included, so no server outlives it holding the port."""
    import ctypes

    pr_set_pdeathsig = 1
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)


class ServeChild:
    """A ``motorbus serve`` child process of the dashboard.

    Args:
        argv: the arguments after ``motorbus serve`` (it must listen on a loopback
            endpoint the dashboard chose: ``--listen tcp/127.0.0.1:PORT``).
    """

    def __init__(self, argv: Sequence[str]) -> None:
        self.argv = [sys.executable, "-m", "motorbus", "serve", *argv]
        self.proc: asyncio.subprocess.Process | None = None
        self.ready_line = ""

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    async def start(self, timeout: float = READY_TIMEOUT_S) -> str:
        """Start the server and wait for its ready line (``serving ... on ENDPOINT``);
        returns that line.  Its standard error is the dashboard's.

        Raises:
            ServeChildError: it ended, or said nothing within ``timeout`` seconds.
        """
        extra: dict[str, Any] = {}
        if sys.platform.startswith("linux"):
            extra["preexec_fn"] = _die_with_parent
        # A session of its own: Ctrl-C on the terminal reaches the dashboard only, which
        # stops its motion first and then ends the server (SIGTERM: its safe ends).
        self.proc = await asyncio.create_subprocess_exec(
            *self.argv,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            start_new_session=True,
            **extra,
        )
        assert self.proc.stdout is not None
        try:
            while True:
                raw = await asyncio.wait_for(self.proc.stdout.readline(), timeout)
                if not raw:
                    code = await self.proc.wait()
                    raise ServeChildError(
                        f"motorbus serve (the dashboard's bus server) ended with status {code} "
                        "before it was ready; its messages are above"
                    )
                line = raw.decode(errors="replace").strip()
                if line.startswith("serving "):
                    self.ready_line = line
                    return line
        except TimeoutError:
            await self.stop()
            raise ServeChildError(
                f"motorbus serve (the dashboard's bus server) said nothing in {timeout:g} s"
            ) from None
        except BaseException:
            await self.stop()
            raise

    async def wait(self) -> int:
        """Until the server ends; its exit status."""
        assert self.proc is not None
        return await self.proc.wait()

    async def stop(self, timeout: float = SERVE_STOP_TIMEOUT_S) -> int | None:
        """End the server with SIGTERM (it sends the safe actions of every lease and
        closes its ports), SIGKILL after ``timeout`` seconds; its exit status."""
        proc = self.proc
        if proc is None:
            return None
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(asyncio.shield(proc.wait()), timeout)
            except TimeoutError:
                log.error("motorbus serve (pid %d) did not end in %g s: killed", proc.pid, timeout)
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
        return await proc.wait()


@dataclass(slots=True)
class Watch:
    """One served bus to watch: the server's name for it (``None``: the only one), the
    page's (``None``: the same), its devices, and the safe action of what the dashboard
    moves (``None``: the served bus's own)."""

    served: str | None
    shown: str | None
    la_ids: list[int]
    project_motor: int | None = None
    quad: bool = False
    la_safe_action: str | None = None

    @classmethod
    def of(
        cls,
        served: str | None,
        shown: str | None,
        devices: Sequence[Any],
        la_ids: list[int],
        safe_action: str | None,
    ) -> Watch:
        """From a bus's device specs (``BusSpec.devices``: ``kind``, ``ids``, ``motor``)."""
        project = next((d.motor for d in devices if d.kind == "project_stepper"), None)
        quad = any(d.kind == "quad_stepper" for d in devices)
        return cls(served, shown, la_ids, project, quad, safe_action)


class SiteLike(Protocol):
    """What :func:`watch_site` uses of ``motorbus.connect``'s site."""

    def bus(self, name: str | None = None) -> Any: ...


def watch_site(
    site: SiteLike,
    watches: Sequence[Watch],
    *,
    endpoint: str,
    period: float,
    control: bool,
    window: tuple[int, int],
) -> ServedDashboard:
    """The dashboard of ``watches`` on the open ``site`` (a bus it does not serve: the
    ``LocalProtocolError`` naming those it does)."""
    setups = []
    for w in watches:
        bus = site.bus(w.served)
        setups.append(
            BusSetup(
                cast(Bus, bus),
                list(w.la_ids),
                w.project_motor,
                w.quad,
                w.la_safe_action or str(bus.safe_action),
                name=w.shown,
            )
        )
    return ServedDashboard(setups, endpoint=endpoint, period=period, control=control, window=window)


#: Where ``free_loopback_endpoint`` looks for a port: below the kernel's ephemeral range.
_LISTEN_PORTS_FROM = 10000


def free_loopback_endpoint() -> str:
    """A Zenoh endpoint on a loopback port that is free now.

    The port is picked at random below the kernel's ephemeral range (Linux:
    ``ip_local_port_range``), where no outgoing connection is given it between this
    check and the server's own bind (a port the kernel handed out for ``bind(port 0)``
    could go to a client's connection meanwhile: "Address already in use", seen with
    many processes connecting at once); failing that, one the kernel picks.
    """
    low = 32768
    with contextlib.suppress(OSError, ValueError):
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    for _ in range(50 if low > _LISTEN_PORTS_FROM + 100 else 0):
        port = random.randrange(_LISTEN_PORTS_FROM, low)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return f"tcp/127.0.0.1:{port}"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def served_name(url: str) -> str:
    """A served bus name (one key chunk) for the port ``url``: ``/dev/ttyUSB0`` ->
    ``dev_ttyUSB0``."""
    out = "".join(c if c.isalnum() or c in "_.-" else "_" for c in url).strip("_")
    return out or "bus"
