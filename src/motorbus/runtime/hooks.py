"""The runtime's side of ``motorbus.lifecycle``: importing this module installs it.

``motorbus/__init__.py`` makes ``motorbus.lifecycle`` import it the first time the
library needs a hook (the first ``Bus.open``, a safe stop, a timer asking about
real-time mode), so nobody has to import it by hand.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

from motorbus import lifecycle
from motorbus.runtime import realtime, shutdown

__all__ = ["RuntimeHooks"]


class RuntimeHooks:
    """Bus opens and closes, safe stops, timers and idle time, as the runtime handles them."""

    def bus_opening(self, bus: object) -> None:
        realtime.on_bus_open()  # MOTORBUS_REALTIME / --realtime, once per process

    def bus_opened(self, bus: object) -> None:
        shutdown.register_bus(bus)  # SIGTERM/SIGHUP protection; a running guard follows

    def bus_closed(self, bus: object) -> None:
        shutdown.unregister_bus(bus)

    def deferred_interrupts(self) -> AbstractContextManager[None]:
        return shutdown.deferred_interrupts()

    def realtime_wanted(self) -> bool:
        return realtime.wanted()

    #: Called on every stream tick: the function itself, one call (``lifecycle.idle``).
    idle = staticmethod(realtime.idle_hook)


lifecycle.install(RuntimeHooks())
