"""Configure motor 1 of the 4-axis stepper controller, run it to done, switch an LED."""

from __future__ import annotations

from _sim import parser, port_or_simulator

import motorbus


async def main(port: str) -> None:
    transport = motorbus.open_transport(port, baudrate=9600)
    async with motorbus.Bus(transport, families=[motorbus.Family.QUAD_STEPPER]) as bus:
        quad = motorbus.QuadStepper(bus)
        await quad.configure(
            1,
            subdivision=8,
            step_angle_x100=180,
            pulses=3200,
            start_hz=200,
            accel_hz=20,
            speed_rpm=300,
        )
        await quad.run(1, timeout=10)  # returns on the controller's "done" reply
        await quad.led(1, True)  # also waits for its "done" reply
        print(f"motor 1 done; {bus.stats.events} done events, {bus.stats.timeouts} timeouts")


if __name__ == "__main__":
    args = parser(__doc__).parse_args()
    with port_or_simulator(args, ["quad-stepper"], 9600) as port:
        motorbus.run(main(port))
