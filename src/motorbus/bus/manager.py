"""Old home of the bus manager, kept so ``motorbus.bus.manager`` imports keep working.

``BusManager`` sits above the bus, the devices and the streams, so it lives in
:mod:`motorbus.manager`; this module only re-exports its public names.  (The layering
test allows this one import from ``bus`` upwards.)
"""

from __future__ import annotations

from motorbus.manager import (
    BusManager,
    BusSpec,
    DeviceSpec,
    DeviceStop,
    StopReport,
    default_bus_file,
    parse_devices,
)

__all__ = [
    "BusManager",
    "BusSpec",
    "DeviceSpec",
    "DeviceStop",
    "StopReport",
    "default_bus_file",
    "parse_devices",
]
