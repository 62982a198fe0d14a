"""The blocking LA actuator: ``InspireLA`` without ``await`` (the steppers are in
``_steppers``, loaded when a program first asks for one).

Every method is the asyncio device's (same arguments, same checks, same docstring),
run on the background loop; tests/blocking/test_api.py checks that each public
coroutine method of the asyncio classes has its blocking counterpart here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from motorbus.blocking._proxy import Proxy, coroutine, plain, wrapped
from motorbus.devices import la as _la
from motorbus.protocol import la

if TYPE_CHECKING:
    from motorbus.blocking._bus import BusView
    from motorbus.devices.calibration import Calibration

__all__ = ["InspireLA"]


def _same_bus(self: Proxy[_la.InspireLA], moved: _la.InspireLA) -> InspireLA:
    assert isinstance(self, InspireLA)
    return InspireLA._on(self.bus, moved)


class InspireLA(Proxy[_la.InspireLA]):
    """One LA actuator on a blocking bus: :class:`motorbus.InspireLA` without ``await``.

    Args:
        bus: an open :class:`motorbus.blocking.Bus` carrying ``Family.LA``, or a
            served one (``motorbus.blocking.connect(...).bus()``).
        id: the actuator ID, 1..254.
        stroke_mm: the stroke of this model in millimetres (enables the ``_mm`` methods).
        calibration: units, soft limits, direction, offset (``motorbus.Calibration``).
        name: the device's name (default ``"la:ID"``), in errors.

    Raises:
        LocalProtocolError: a bad ``id``, ``stroke_mm``, ``calibration`` or ``name``
            (nothing is sent).
    """

    _bus: BusView[Any]

    def __init__(
        self,
        bus: BusView[Any],
        id: int,
        *,
        stroke_mm: float | None = None,
        calibration: Calibration | None = None,
        name: str | None = None,
    ) -> None:
        self._aio = _la.InspireLA(
            bus._any, id, stroke_mm=stroke_mm, calibration=calibration, name=name
        )
        self._runner = bus._runner
        self._bus = bus

    @classmethod
    def _on(cls, bus: BusView[Any], aio: _la.InspireLA) -> InspireLA:
        proxy = cls._of(aio, bus._runner)
        proxy._bus = bus
        return proxy

    @property
    def bus(self) -> BusView[Any]:
        """The blocking bus the actuator is on."""
        return self._bus

    @property
    def id(self) -> int:
        """The actuator ID."""
        return self._aio.id

    @property
    def stroke_mm(self) -> float | None:
        """The stroke in millimetres, if given."""
        return self._aio.stroke_mm

    @property
    def key(self) -> str:
        """The device key, ``"la:ID"`` (stats, leases)."""
        return self._aio.key

    @property
    def name(self) -> str:
        """The device's name (a bus file's ``[bus.la.NAME]``), else ``"la:ID"``."""
        return self._aio.name

    @property
    def calibration(self) -> Calibration:
        """Units, soft limits, stroke: every move is checked against the limits."""
        return self._aio.calibration

    @property
    def unit(self) -> str:
        """The unit of positions given without one (``raw`` unless calibrated)."""
        return self._aio.unit

    to_unit = plain(_la.InspireLA.to_unit)
    from_unit = plain(_la.InspireLA.from_unit)
    position_in = coroutine(_la.InspireLA.position_in)

    to_mm = plain(_la.InspireLA.to_mm)
    from_mm = plain(_la.InspireLA.from_mm)
    safe_stop_commands = plain(_la.InspireLA.safe_stop_commands)

    position_mm = coroutine(_la.InspireLA.position_mm)

    def move_to_mm(self, mm: float, **kwargs: Any) -> la.Status | None:
        return self._runner.call(self._aio.move_to_mm(mm, **kwargs))

    move_to_mm.__doc__ = _la.InspireLA.move_to_mm.__doc__

    release = coroutine(_la.InspireLA.release)
    status = coroutine(_la.InspireLA.status)
    move_to = coroutine(_la.InspireLA.move_to)
    follow = coroutine(_la.InspireLA.follow)
    enable = coroutine(_la.InspireLA.enable)
    estop = coroutine(_la.InspireLA.estop)
    pause = coroutine(_la.InspireLA.pause)
    save = coroutine(_la.InspireLA.save)
    clear_fault = coroutine(_la.InspireLA.clear_fault)
    recover = coroutine(_la.InspireLA.recover)
    read = coroutine(_la.InspireLA.read)
    write = coroutine(_la.InspireLA.write)
    read_table = coroutine(_la.InspireLA.read_table)
    write_table = coroutine(_la.InspireLA.write_table)
    position = coroutine(_la.InspireLA.position)
    target = coroutine(_la.InspireLA.target)
    force = coroutine(_la.InspireLA.force)
    raw_force = coroutine(_la.InspireLA.raw_force)
    zero_force_sensor = coroutine(_la.InspireLA.zero_force_sensor)
    over_current_limit = coroutine(_la.InspireLA.over_current_limit)
    set_over_current_limit = coroutine(_la.InspireLA.set_over_current_limit)
    temperature_limits = coroutine(_la.InspireLA.temperature_limits)
    set_temperature_limits = coroutine(_la.InspireLA.set_temperature_limits)
    baud_code = coroutine(_la.InspireLA.baud_code)
    set_baud_code = coroutine(_la.InspireLA.set_baud_code)
    change_id = wrapped(_la.InspireLA.change_id, _same_bus)
