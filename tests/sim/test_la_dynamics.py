"""The LA model's rig options: dead time, first-order lag, dead band, position noise."""

from __future__ import annotations

import math
import statistics

import pytest

from motorbus.errors import LocalProtocolError
from motorbus.protocol.la import Control, ControlAction, Follow, MoveTo, Status, decode_reply
from motorbus.sim.la import LAModel


def query(model: LAModel, now: float) -> Status:
    (frame,) = model.handle(Control(model.id, ControlAction.QUERY_STATUS).encode(), now)
    status = decode_reply(frame)
    assert isinstance(status, Status)
    return status


def test_dead_time_delays_the_motion_not_the_target() -> None:
    model = LAModel(1, position=500, dead_time=0.015)
    model.handle(MoveTo(1, 1500).encode(), 1.0)
    early = query(model, 1.0149)
    assert early.target == 1500
    assert early.position == 500
    assert query(model, 1.030).position > 500


def test_a_pause_drops_a_command_still_in_its_dead_time() -> None:
    model = LAModel(1, position=500, dead_time=0.050)
    model.handle(MoveTo(1, 1500).encode(), 1.0)
    model.handle(Control(1, ControlAction.PAUSE).encode(), 1.01)
    assert query(model, 2.0).position == 500


@pytest.mark.parametrize(("start", "end"), [(500, 1000), (1500, 1000)])
def test_dead_band_stops_short_along_the_approach(start: int, end: int) -> None:
    model = LAModel(1, position=start, dead_band=6.0)
    model.handle(MoveTo(1, end).encode(), 0.0)
    settled = query(model, 2.0)
    assert settled.position == end - math.copysign(3, end - start)
    assert not model.moving
    # A target within the band does not move the motor.
    model.handle(MoveTo(1, settled.position + 2).encode(), 2.0)
    assert query(model, 3.0).position == settled.position


def test_first_order_lag_in_follow_mode() -> None:
    tau = 0.05
    model = LAModel(1, position=0, lag_tau=tau, stroke_speed=1e6)
    model.handle(Follow(1, 1000).encode(), 0.0)
    # After one time constant a first-order lag has covered 1 - 1/e of the step.
    assert query(model, tau).position == pytest.approx(1000 * (1 - math.exp(-1)), abs=10)
    assert query(model, 10 * tau).position == pytest.approx(1000, abs=1)


def test_position_noise_has_the_configured_spread_and_repeats() -> None:
    def readings(seed: int) -> list[int]:
        model = LAModel(1, position=1000, position_noise=4.0, seed=seed)
        return [query(model, i * 0.001).position for i in range(2000)]

    a = readings(7)
    assert readings(7) == a
    assert statistics.pstdev(a) == pytest.approx(4.0, rel=0.1)
    assert statistics.mean(a) == pytest.approx(1000, abs=0.5)


@pytest.mark.parametrize("field", ["dead_time", "lag_tau", "dead_band", "position_noise"])
def test_rig_options_refuse_negative_values(field: str) -> None:
    with pytest.raises(LocalProtocolError, match=f"{field} must be a number >= 0, got -1"):
        LAModel(1, **{field: -1})
