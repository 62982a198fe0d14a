"""A live dashboard in the browser: every bus and device at a glance (``motorbus dashboard``).

``state`` is the pure model (observations in, JSON snapshots out), ``runtime`` the
pollers (one per bus, however many viewers), controls and recording, ``record`` the
frame-log and CSV writer, ``server`` the aiohttp application (needs the ``dashboard``
extra: ``pip install 'motorbus[dashboard]'``; it is not imported here, so the rest
works without aiohttp).  docs/dashboard.md describes the page.
"""

from __future__ import annotations

from motorbus.dashboard.record import Recorder as Recorder
from motorbus.dashboard.runtime import BusSetup as BusSetup
from motorbus.dashboard.runtime import ControlError as ControlError
from motorbus.dashboard.runtime import Dashboard as Dashboard
from motorbus.dashboard.state import DashboardState as DashboardState

__all__ = [
    "BusSetup",
    "ControlError",
    "Dashboard",
    "DashboardState",
    "Recorder",
]
