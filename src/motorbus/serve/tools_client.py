"""The client side of ``motorbus.serve.tools_server``: what a served bus knows of its
devices (``fetch_devices``), a scan through the server (``scan_served``) and the frames
it writes and reads (``frame_batches``); ``ServedBus.fetch_devices``, ``.scan`` and
``.frames`` are these."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from motorbus.bus.occupancy import BusTiming, command_occupancy
from motorbus.devices.la_scan import SCAN_BUDGET_MAX_S, SCAN_HOST_ALLOWANCE_S, SCAN_PASSES_MAX
from motorbus.errors import LocalProtocolError, RemoteProtocolError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int
from motorbus.serve import keys as k
from motorbus.serve.zconf import on_zenoh_thread

__all__ = ["ServedDevices", "ServedScan", "fetch_devices", "frame_batches", "scan_served"]


def _la_ids(keys: list[str]) -> tuple[int, ...]:
    ids = {int(key[3:]) for key in keys if key.startswith("la:") and key[3:].isdigit()}
    return tuple(sorted(i for i in ids if 1 <= i <= 254))


@dataclass(frozen=True, slots=True)
class ServedDevices:
    """The answer of a bus's ``devices`` query.

    Attributes:
        declared: the device keys its bus file or ``--devices`` declares.
        answered: the device keys that have answered the bus since it opened.
        timing: the bus's timing (baud, spacing, host margin, turnarounds).
        now: the server bus's clock when it answered (seconds).
        frames_tapped: the server publishes the bus's frames (someone subscribes).
    """

    declared: tuple[str, ...]
    answered: tuple[str, ...]
    timing: BusTiming
    now: float = 0.0
    frames_tapped: bool = False
    raw: dict[str, Any] = field(default_factory=dict)

    @property
    def declared_la(self) -> tuple[int, ...]:
        return _la_ids(list(self.declared))

    @property
    def answered_la(self) -> tuple[int, ...]:
        return _la_ids(list(self.answered))

    @property
    def known_la(self) -> tuple[int, ...]:
        """The LA IDs the server knows: declared, or answered it."""
        return _la_ids([*self.declared, *self.answered])


async def fetch_devices(bus: Any) -> ServedDevices:
    """Ask the server what bus ``bus`` declares and what answered it (nothing is sent
    on the bus)."""
    result = await bus._query("devices", {})
    try:
        t = result["timing"]
        timing = BusTiming(
            int(t["baud"]),
            float(t["min_spacing_s"]),
            float(t["host_margin_s"]),
            {Family(f): float(s) for f, s in t["turnaround_s"].items()},
        )
        return ServedDevices(
            tuple(str(x) for x in result["declared"]),
            tuple(str(x) for x in result["answered"]),
            timing,
            float(result["now"]),
            bool(result["frames_tapped"]),
            result,
        )
    except (KeyError, TypeError, ValueError) as err:
        raise LocalProtocolError(
            f"the server's devices answer did not decode: {err!r}", field="devices"
        ) from None


@contextlib.asynccontextmanager
async def frame_batches(bus: Any) -> AsyncIterator[asyncio.Queue[dict[str, Any]]]:
    """Subscribe to the frames bus ``bus`` writes and reads: a queue of the server's
    batches (``{"time", "frames": [[t, "tx" | "rx", HEX], ...]}``, ``t`` and ``time`` on
    the server bus's clock).  The server taps its bus only while someone subscribes."""
    site = bus.site
    session = site._session
    if session is None:
        raise LocalProtocolError(f"the connection to {site.endpoint} is closed", field="bus")
    loop = asyncio.get_running_loop()
    batches: asyncio.Queue[dict[str, Any]] = asyncio.Queue()

    def on_sample(sample: Any) -> None:
        try:
            body = k.decode_json(sample.payload.to_bytes())
        except LocalProtocolError:
            return
        with contextlib.suppress(RuntimeError):  # the loop closed
            loop.call_soon_threadsafe(batches.put_nowait, body)

    key = k.bus_key(bus.name, "frames")
    subscriber = session.declare_subscriber(key, on_zenoh_thread(on_sample))
    try:
        yield batches
    finally:
        with contextlib.suppress(Exception):
            subscriber.undeclare()


@dataclass(frozen=True, slots=True)
class ServedScan:
    """What a scan through a server found.

    Attributes:
        declared: the LA IDs the server's bus declares.
        asked: the IDs sent a status query.
        found: those that answered, ascending.
        budget_s: the first pass's budget per ID (a deadline on the server's bus).
        requests: status queries sent; misses: those not answered.
    """

    declared: tuple[int, ...]
    asked: tuple[int, ...]
    found: tuple[int, ...]
    budget_s: float
    requests: int = 0
    misses: int = 0


def _status_query(ident: int) -> la.Control:
    return la.Control(ident, la.ControlAction.QUERY_STATUS)


async def scan_served(
    bus: Any,
    ids: Sequence[int] | None = None,
    *,
    timeout: float | None = None,
    passes: int = SCAN_PASSES_MAX,
) -> ServedScan:
    """Status queries through the server to ``ids`` (default: the LA IDs it knows, from
    its ``devices`` query), one at a time among the application's requests.

    The per-ID budget (a deadline on the server's bus, from the completed write) is
    ``timeout`` if given, else the status query's wire time and the LA's turnaround on
    the server's bus plus the scan's host allowance, at least ``SCAN_BUDGET_MAX_S``;
    with two passes the IDs that did not answer are asked again with twice that.

    Raises:
        LocalProtocolError: a bad ID, ``timeout`` or ``passes`` (nothing sent).
    """
    asked_ids = (
        None if ids is None else tuple(check_int("id", i, la.ID_MIN, la.ID_MAX) for i in ids)
    )
    check_int("passes", passes, 1, SCAN_PASSES_MAX)
    if timeout is not None and (
        isinstance(timeout, bool) or not isinstance(timeout, int | float) or not timeout > 0
    ):
        raise LocalProtocolError(
            f"timeout={timeout!r} must be a positive number of seconds",
            field="timeout",
            value=timeout,
        )
    devices = await fetch_devices(bus)
    asked = asked_ids if asked_ids is not None else devices.known_la
    occupancy = command_occupancy(devices.timing, _status_query(la.ID_MIN))
    floor = occupancy.budget - occupancy.margin + SCAN_HOST_ALLOWANCE_S
    budget = timeout if timeout is not None else max(SCAN_BUDGET_MAX_S, 2 * floor)
    found: set[int] = set()
    remaining = list(asked)
    requests = misses = 0
    for n in range(passes):
        for ident in remaining:
            requests += 1
            try:
                await bus.request(_status_query(ident), timeout=budget * (1 + n), retries=0)
            except (ReplyTimeoutError, RemoteProtocolError):
                misses += 1
                continue
            found.add(ident)
        remaining = [i for i in remaining if i not in found]
        if not remaining:
            break
    return ServedScan(devices.declared_la, asked, tuple(sorted(found)), budget, requests, misses)
