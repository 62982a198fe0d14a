"""The blocking stepper controllers: ``ProjectStepper`` and ``QuadStepper`` without
``await``, in a module of their own so that an LA program loads neither protocol.

Every method is the asyncio device's (same arguments, same checks, same docstring),
run on the background loop; tests/blocking/test_api.py checks that each public
coroutine method of the asyncio classes has its blocking counterpart here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from motorbus.blocking._proxy import Proxy, coroutine, plain
from motorbus.devices import project_stepper as _ps
from motorbus.devices import quad_stepper as _qs
from motorbus.protocol import project_stepper as ps

if TYPE_CHECKING:
    from motorbus.blocking._bus import BusView

__all__ = ["ProjectStepper", "QuadStepper"]


class ProjectStepper(Proxy[_ps.ProjectStepper]):
    """The 11-byte ``FF AA`` project stepper controller on a blocking bus:
    :class:`motorbus.ProjectStepper` without ``await``.

    Args:
        bus: an open :class:`motorbus.blocking.Bus` carrying ``Family.PROJECT_STEPPER``, or a
            served one (``motorbus.blocking.connect(...).bus()``).
        motor: the motor byte of motor-addressed commands (default 0x03).
    """

    _bus: BusView[Any]

    def __init__(self, bus: BusView[Any], *, motor: int = ps.DEFAULT_MOTOR) -> None:
        self._aio = _ps.ProjectStepper(bus._any, motor=motor)
        self._runner = bus._runner
        self._bus = bus

    @property
    def bus(self) -> BusView[Any]:
        """The blocking bus the controller is on."""
        return self._bus

    @property
    def motor(self) -> int:
        """The motor byte of motor-addressed commands."""
        return self._aio.motor

    safe_stop_commands = plain(_ps.ProjectStepper.safe_stop_commands)

    release = coroutine(_ps.ProjectStepper.release)
    upload = coroutine(_ps.ProjectStepper.upload)
    check_project = coroutine(_ps.ProjectStepper.check_project)
    read_project = coroutine(_ps.ProjectStepper.read_project)
    save_project = coroutine(_ps.ProjectStepper.save_project)
    clear_project = coroutine(_ps.ProjectStepper.clear_project)
    start_project = coroutine(_ps.ProjectStepper.start_project)
    run_project = coroutine(_ps.ProjectStepper.run_project)
    stop_project = coroutine(_ps.ProjectStepper.stop_project)
    jog = coroutine(_ps.ProjectStepper.jog)
    single_run = coroutine(_ps.ProjectStepper.single_run)
    home = coroutine(_ps.ProjectStepper.home)
    stop = coroutine(_ps.ProjectStepper.stop)
    set_stop_mode = coroutine(_ps.ProjectStepper.set_stop_mode)
    set_output = coroutine(_ps.ProjectStepper.set_output)
    read_input = coroutine(_ps.ProjectStepper.read_input)
    set_mode4 = coroutine(_ps.ProjectStepper.set_mode4)
    set_power_on_homing = coroutine(_ps.ProjectStepper.set_power_on_homing)


class QuadStepper(Proxy[_qs.QuadStepper]):
    """The 9-byte ``FF AA`` 4-axis stepper controller on a blocking bus:
    :class:`motorbus.QuadStepper` without ``await``.

    Args:
        bus: an open :class:`motorbus.blocking.Bus` carrying ``Family.QUAD_STEPPER``, or a
            served one (``motorbus.blocking.connect(...).bus()``).
    """

    _bus: BusView[Any]

    def __init__(self, bus: BusView[Any]) -> None:
        self._aio = _qs.QuadStepper(bus._any)
        self._runner = bus._runner
        self._bus = bus

    @property
    def bus(self) -> BusView[Any]:
        """The blocking bus the controller is on."""
        return self._bus

    safe_stop_commands = plain(_qs.QuadStepper.safe_stop_commands)

    release = coroutine(_qs.QuadStepper.release)
    configure = coroutine(_qs.QuadStepper.configure)
    run = coroutine(_qs.QuadStepper.run)
    run_all = coroutine(_qs.QuadStepper.run_all)
    stop = coroutine(_qs.QuadStepper.stop)
    stop_all = coroutine(_qs.QuadStepper.stop_all)
    home = coroutine(_qs.QuadStepper.home)
    led = coroutine(_qs.QuadStepper.led)
    save = coroutine(_qs.QuadStepper.save)
