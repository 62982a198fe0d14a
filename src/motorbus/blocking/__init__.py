"""motorbus without ``await``: the same buses, devices and streams, for scripts,
notebooks and control loops written as plain loops.

::

    import motorbus
    import motorbus.blocking as mb

    with mb.Bus(motorbus.open_transport("/dev/ttyUSB0", baudrate=921600),
                families=[motorbus.Family.LA]) as bus:
        actuator = mb.InspireLA(bus, 1, stroke_mm=30)
        actuator.enable()
        actuator.move_to(1500, wait=True)

Every object here is a thin view of its asyncio counterpart, which runs on one
background event loop thread of the process (``asyncio.run_coroutine_threadsafe``):
the spacing, deadlines, retries, leases and safe ends are the asyncio bus's own,
unchanged.  It works where an event loop already runs in the calling thread (Jupyter).
Closing a bus (``close()``, the end of its ``with`` block however it is left, or the
interpreter's exit) runs the same safe ends as the asyncio ``async with Bus`` exit; a
Ctrl-C while a call waits cancels the call, closes every open bus safely and is raised
again.

A served bus (``motorbus serve``) is one line away: ``with mb.connect(ENDPOINT).bus()
as bus:`` in place of ``with mb.Bus(...) as bus:``, and the rest of the program stays
(the ``serve`` extra).  See docs/blocking.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from motorbus.protocol.exports import lazy_names

# Names load on first use: an LA program loads neither stepper nor, without a server,
# Zenoh (its first line took 0.22 s with them, 0.17 s without: bench_startup.py).
_EXPORTS = {
    "motorbus.blocking._bus": ("Bus", "BusManager", "BusView", "Lease", "read_statuses"),
    "motorbus.blocking._devices": ("InspireLA",),
    "motorbus.blocking._steppers": ("ProjectStepper", "QuadStepper"),
    "motorbus.blocking._events": ("EventHub", "Subscription"),
    "motorbus.blocking._served": ("FrameFeed", "ServedBus", "ServedSite", "connect"),
    "motorbus.blocking._streams": ("Setpoint", "Stream", "Streamer"),
}

if TYPE_CHECKING:
    from motorbus.blocking._bus import Bus as Bus
    from motorbus.blocking._bus import BusManager as BusManager
    from motorbus.blocking._bus import BusView as BusView
    from motorbus.blocking._bus import Lease as Lease
    from motorbus.blocking._bus import read_statuses as read_statuses
    from motorbus.blocking._devices import InspireLA as InspireLA
    from motorbus.blocking._events import EventHub as EventHub
    from motorbus.blocking._events import Subscription as Subscription
    from motorbus.blocking._served import FrameFeed as FrameFeed
    from motorbus.blocking._served import ServedBus as ServedBus
    from motorbus.blocking._served import ServedSite as ServedSite
    from motorbus.blocking._served import connect as connect
    from motorbus.blocking._steppers import ProjectStepper as ProjectStepper
    from motorbus.blocking._steppers import QuadStepper as QuadStepper
    from motorbus.blocking._streams import Setpoint as Setpoint
    from motorbus.blocking._streams import Stream as Stream
    from motorbus.blocking._streams import Streamer as Streamer

if not TYPE_CHECKING:  # (type checkers read the imports above: a misspelt name is caught)
    __all__, __getattr__, __dir__ = lazy_names(__name__, _EXPORTS)
