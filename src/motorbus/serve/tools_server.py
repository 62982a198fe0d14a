"""What the command-line tools ask of a served bus, beside requests and leases.

Two keys per bus (``motorbus.serve.keys``; docs/serve.md lists the payloads):

* ``motorbus/v1/bus/{bus}/devices`` (query): the devices the server's bus file or
  ``--devices`` declares, the devices that have answered the bus since it opened (its
  counters), and the bus's timing: ``motorbus scan --connect``, ``monitor --connect``
  without ``--ids`` and ``doctor --connect`` start from it, sending nothing.
* ``motorbus/v1/bus/{bus}/frames`` (publication): every frame the bus writes and every
  chunk of bytes it reads, for ``motorbus capture --connect``.  Only while some
  subscriber matches the publisher (Zenoh's matching status): then a wire tap on the
  bus appends each chunk to a list (no encoding, no I/O on the bus's path), and a task
  publishes the list every ``FLUSH_S`` as one JSON batch.  With no subscriber there is
  no tap and no task.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from motorbus.bus.bus import Bus
from motorbus.serve import keys as k

__all__ = ["FLUSH_S", "FrameFeed", "ToolsService", "frames_batch"]

#: How often a frame feed publishes what its tap gathered (seconds).
FLUSH_S = 0.02

Item = tuple[float, bool, bytes]


def frames_batch(now: float, items: Sequence[Item]) -> dict[str, Any]:
    """The JSON body of one ``frames`` publication: the bus clock's ``time`` when it was
    published and each chunk as ``[t, "tx" | "rx", HEX]`` in wire order."""
    return {
        "time": now,
        "frames": [[t, "tx" if out else "rx", bytes(data).hex()] for t, out, data in items],
    }


class FrameFeed:
    """One bus's ``frames`` publication (see the module docstring)."""

    def __init__(self, bus: Bus, publisher: Any) -> None:
        self.bus = bus
        self.publisher = publisher
        self.items: list[Item] = []
        self.active = False
        self.closed = False  # the server is closing: never tapped again
        #: Batches published so far.
        self.published = 0
        self._task: asyncio.Task[None] | None = None

    def tap(self, outgoing: bool, data: bytes, at: float) -> None:
        """The wire tap: one append (the bus calls it on its own path; ``bytes`` of a
        ``bytes`` is the same object, of a reused buffer a copy)."""
        self.items.append((at, outgoing, bytes(data)))

    def matching(self, status: Any) -> None:
        """Zenoh's matching status changed: tap the bus while someone subscribes."""
        self.set_active(bool(getattr(status, "matching", status)))

    def set_active(self, active: bool) -> None:
        if active and not self.active and not self.closed:
            self.active = True
            self.bus.add_wire_tap(self.tap)
            self._task = asyncio.ensure_future(self._run())
        elif not active and self.active:
            self.active = False
            self.bus.remove_wire_tap(self.tap)
            if self._task is not None:
                self._task.cancel()
                self._task = None
            self.flush()

    def flush(self) -> None:
        """Publish what the tap gathered since the last batch (nothing if nothing)."""
        items, self.items = self.items, []
        if not items:
            return
        with contextlib.suppress(Exception):  # a closing session: the batch is lost
            self.publisher.put(k.encode_json(frames_batch(self.bus.timer.now(), items)))
            self.published += 1

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(FLUSH_S)
            self.flush()


class ToolsService:
    """The ``devices`` queries and ``frames`` publications of a server's buses.

    Args:
        buses: the served buses by name.
        devices: the device keys each bus declares (``la:3``, ``project_stepper``,
            ``quad_stepper``), by bus name.
    """

    def __init__(self, buses: Mapping[str, Bus], devices: Mapping[str, Sequence[str]]) -> None:
        self.buses = buses
        self.devices = {name: tuple(keys) for name, keys in devices.items()}
        self.feeds: dict[str, FrameFeed] = {}

    def start(
        self,
        session: Any,
        on_query: Callable[..., Callable[[Any], None]],
        threadsafe: Callable[[Callable[[Any], None]], Callable[[Any], None]],
    ) -> list[Any]:
        """Declare the keys of every bus; returns the Zenoh entities to keep."""
        entities: list[Any] = []
        for name, bus in self.buses.items():
            entities.append(
                session.declare_queryable(k.bus_key(name, "devices"), on_query(self.answer, name))
            )
            publisher = session.declare_publisher(k.bus_key(name, "frames"))
            feed = self.feeds[name] = FrameFeed(bus, publisher)
            entities.append(publisher)
            entities.append(publisher.declare_matching_listener(threadsafe(feed.matching)))
            feed.set_active(bool(publisher.matching_status.matching))
        return entities

    def close(self) -> None:
        """Untap every bus and publish what is left."""
        for feed in self.feeds.values():
            feed.closed = True
            feed.set_active(False)

    async def answer(self, name: str, payload: dict[str, Any]) -> dict[str, Any]:
        """The ``devices`` query of bus ``name``."""
        bus = self.buses[name]
        timing = bus.timing
        feed = self.feeds.get(name)
        return {
            "now": bus.timer.now(),
            "frames_tapped": feed is not None and feed.active,
            "declared": list(self.devices.get(name, ())),
            "answered": sorted(key for key, d in bus.stats.devices.items() if d.replies),
            "timing": {
                "baud": timing.baud,
                "min_spacing_s": timing.min_spacing,
                "host_margin_s": timing.host_margin,
                "turnaround_s": {f.value: s for f, s in timing.turnaround.items()},
            },
        }
