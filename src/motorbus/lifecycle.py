"""The seam between the library and the process runtime (``motorbus.runtime``).

The library (the bus, the devices, the streams) needs four things of the process it
runs in, and imports none of the code that provides them:

* a bus that opens or closes says so: before its port opens (``bus_opening``: the
  runtime applies real-time mode if it was asked for), once it is open
  (``bus_opened``: the runtime protects it against SIGTERM, SIGHUP and a second
  Ctrl-C and lets a running guard process follow it) and once it is closed (``bus_closed``);
* a safe stop runs inside ``deferred_interrupts()``, so a second Ctrl-C cannot cut it
  short;
* a timer asks whether real-time mode is on or asked for (``realtime_wanted``);
* a stream's tick loop hands its idle time to the runtime (``idle``: real-time mode
  runs the garbage collector's full collections there).

The runtime fills this seam with :func:`install`.  Nobody has to import it for that:
``motorbus``'s package ``__init__`` (which Python runs before any ``motorbus.*``
module) names the runtime's loader with :func:`set_loader`, and the first call that
needs a hook loads it.  So a program that only opens a ``Bus`` is stopped safely on
SIGTERM, exactly as one that runs ``motorbus.run``.  Without any runtime (a loader set
to None and nothing installed) the hooks do nothing, and the first bus that opens says
so in a warning.

Pure: no asyncio, no signals, no clock.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Protocol

__all__ = [
    "ProcessHooks",
    "bus_closed",
    "bus_opened",
    "bus_opening",
    "deferred_interrupts",
    "idle",
    "install",
    "installed",
    "realtime_wanted",
    "set_loader",
]

log = logging.getLogger("motorbus.lifecycle")


class ProcessHooks(Protocol):
    """What the runtime provides (``motorbus.runtime.hooks.RuntimeHooks``)."""

    def bus_opening(self, bus: object) -> None:
        """A bus is about to open its port (an error raised here keeps it closed)."""

    def bus_opened(self, bus: object) -> None:
        """A bus opened, inside its running loop."""

    def bus_closed(self, bus: object) -> None:
        """A bus closed (its port too)."""

    def deferred_interrupts(self) -> AbstractContextManager[None]:
        """Hold stop signals while a safe stop runs; deliver them afterwards."""

    def realtime_wanted(self) -> bool:
        """Whether real-time mode is on or asked for."""

    def idle(self, budget_s: float) -> object:
        """The caller is idle for about ``budget_s`` seconds (a stream's tick loop, on
        every tick: keep it one call)."""


_hooks: ProcessHooks | None = None
_loader: Callable[[], None] | None = None
_warned = False


def install(hooks: ProcessHooks | None) -> ProcessHooks | None:
    """Make ``hooks`` the process's hooks (None: none); returns the previous ones."""
    global _hooks, idle
    previous, _hooks = _hooks, hooks
    idle = hooks.idle if hooks is not None else _idle_loading
    return previous


def set_loader(loader: Callable[[], None] | None) -> None:
    """Call ``loader`` the first time a hook is needed and none is installed (it is
    expected to ``install`` them).  ``motorbus/__init__.py`` sets the runtime's."""
    global _loader
    _loader = loader


def installed() -> ProcessHooks | None:
    """The hooks, loading the runtime first if none is installed yet."""
    global _loader
    if _hooks is None and _loader is not None:
        loader, _loader = _loader, None
        loader()
    return _hooks


def bus_opening(bus: object) -> None:
    """Called by ``Bus.open`` before its port opens."""
    global _warned
    hooks = installed()
    if hooks is not None:
        hooks.bus_opening(bus)
    elif not _warned:
        _warned = True
        log.warning(
            "no process runtime is installed (motorbus.lifecycle): a signal will not "
            "stop the motion of bus %s safely",
            getattr(bus, "name", bus),
        )


def bus_opened(bus: object) -> None:
    """Called by ``Bus.open`` once its port is open."""
    hooks = installed()
    if hooks is not None:
        hooks.bus_opened(bus)


def bus_closed(bus: object) -> None:
    """Called by ``Bus.close`` once its port is closed."""
    hooks = _hooks  # a bus that opened loaded them; nothing to load for a close
    if hooks is not None:
        hooks.bus_closed(bus)


def deferred_interrupts() -> AbstractContextManager[None]:
    """Around every safe stop (``motorbus.runtime.shutdown.deferred_interrupts``)."""
    hooks = installed()
    if hooks is None:
        return contextlib.nullcontext()
    return hooks.deferred_interrupts()


def realtime_wanted() -> bool:
    """Whether real-time mode is on or asked for (False without a runtime)."""
    hooks = installed()
    return hooks is not None and hooks.realtime_wanted()


def _idle_loading(budget_s: float) -> object:
    hooks = installed()
    return None if hooks is None else hooks.idle(budget_s)


#: ``idle(budget_s)``: a tick loop is idle for about ``budget_s`` seconds (a no-op
#: without a runtime).  The installed hooks' own ``idle`` once there are any: the tick
#: loop calls it on every tick, so it costs one call, as before the seam.
idle: Callable[[float], object] = _idle_loading
