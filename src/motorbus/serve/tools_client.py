"""The client side of ``motorbus.serve.tools_server``: what a served bus knows of its
devices (``fetch_devices``) and the frames it writes and reads (``frame_batches``)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

from motorbus.bus.occupancy import BusTiming
from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Family
from motorbus.serve import keys as k
from motorbus.serve.client import ServedBus

__all__ = ["ServedDevices", "fetch_devices", "frame_batches"]


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


async def fetch_devices(bus: ServedBus | Any) -> ServedDevices:
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
async def frame_batches(bus: ServedBus | Any) -> AsyncIterator[asyncio.Queue[dict[str, Any]]]:
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

    subscriber = session.declare_subscriber(k.bus_key(bus.name, "frames"), on_sample)
    try:
        yield batches
    finally:
        with contextlib.suppress(Exception):
            subscriber.undeclare()
