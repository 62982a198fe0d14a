"""Actuators at their own rates, connected one at a time (what ``la setup`` meets)."""

from __future__ import annotations

from motorbus.protocol import la
from motorbus.sim.bus import SimBus
from motorbus.sim.la import LAModel

QUERY = la.control_frame(1, la.ControlAction.QUERY_STATUS).encode()


def _answers(bus: SimBus, now: float) -> int:
    before = bus.stats.replies
    bus.receive(QUERY, now)
    return bus.stats.replies - before


def test_each_actuator_hears_only_at_its_own_rate() -> None:
    slow, fast = LAModel(1, baud_code=la.BaudCode.B19200), LAModel(1)
    bus = SimBus([slow, fast], baud=921600, device_bauds=True, pacing="prompt")
    bus.unplug(1)
    assert _answers(bus, 0.0) == 0  # the host at 921600: the 19200 actuator reads garbage
    bus.set_line_rate(19200)
    assert _answers(bus, 1.0) == 1
    # Without device_bauds every model hears, whatever its baud code.
    assert _answers(SimBus([LAModel(1, baud_code=0)], baud=921600, pacing="prompt"), 0.0) == 1


def test_plugging_in_powers_up_afresh_so_a_saved_baud_takes_effect() -> None:
    model = LAModel(1)
    bus = SimBus([model], baud=921600, device_bauds=True, pacing="prompt")
    model.set_register(la.Register.BAUD, int(la.BaudCode.B57600))
    model.handle(la.control_frame(1, la.ControlAction.SAVE).encode(), 0.0)
    assert _answers(bus, 0.1) == 1  # saved, but the new rate needs a power cycle
    bus.unplug(0)
    assert _answers(bus, 0.2) == 0  # unplugged: silent
    bus.plug(0, 0.3)
    assert model.baud == 57600 and _answers(bus, 0.4) == 0
    bus.set_line_rate(57600)
    assert _answers(bus, 0.5) == 1


def test_an_end_stop_stops_the_motor_with_a_stall() -> None:
    model = LAModel(1, position=1000, travel_min=300, travel_max=1700)
    model.handle(la.MoveTo(1, 100, True).encode(), 0.0)
    assert model.status(5.0).position == 300 and model.errors == la.ErrorFlags.STALL
    try:
        LAModel(1, travel_min=500, travel_max=400)
    except ValueError as err:
        assert "travel_max=400 is out of range" in str(err)
    else:
        raise AssertionError("travel_max below travel_min was accepted")
