"""Device variants the manuals allow, as model options: every device test runs against each.

Where a manual leaves a reply open (docs/protocols.md ambiguity ids in brackets), a real
device may do either, so the drivers must work with both:

* LA: a write is answered with the 22-byte status or the short ack [A2-03]; status byte 4
  is 0x04 or echoes the request's command [A2-04]; an ID change is answered from the old
  or the new ID [A2-12]; latency is 120 us typical or up to 800 us every time [A2-15].
* Quad stepper: run acks and done replies carry address 0x00 or the motor number [A1-02];
  motors started by run-all each send a done reply, or none [A1-04].
* Project stepper: the 0x5E/0x9E/0xAE reply has 00 in byte 3 or echoes the request's value
  [A0-04, A0-13]; ``EE DD`` is or is not also sent (here 0.1 s) after a running project
  is stopped [A0-06].
"""

from __future__ import annotations

import itertools
from typing import Any

import pytest

from motorbus.sim.la import TURNAROUND_MAX_S


def _la_variants() -> list[Any]:
    out = []
    for write_reply, echo, id_reply in itertools.product(
        ("status", "ack"), ("0x04", "request"), ("old", "new")
    ):
        options = {"write_reply": write_reply, "status_cmd_echo": echo, "id_change_reply": id_reply}
        out.append(pytest.param(options, id=f"write-{write_reply}-echo-{echo}-id-{id_reply}"))
    # The slowest latency the manual allows, on every reply.
    slow = {"turnaround_typical": TURNAROUND_MAX_S, "slow_turnaround_probability": 0.0}
    out.append(pytest.param(slow, id="slowest-latency"))
    return out


#: ``LAModel(**options)`` variants.
LA_VARIANTS = _la_variants()
#: ``QuadStepperModel(**options)`` variants.
QUAD_VARIANTS = [
    pytest.param({"run_ack_address": address, "run_all_done": done}, id=f"ack-{address}-all-{done}")
    for address, done in itertools.product(("zero", "motor"), ("each", "none"))
]
#: ``ProjectStepperModel(**options)`` variants.
PROJECT_VARIANTS = [
    pytest.param({}, id="as-printed"),
    pytest.param({"global_reply_echo": "value"}, id="global-echo-value"),
    # EE DD 0.1 s after a stop, as from a controller that decelerates before it reports.
    pytest.param({"ee_dd_after_stop_s": 0.1}, id="ee-dd-after-stop"),
]
