"""One LA actuator: status, a positioning move, a register, and the fault flags."""

from __future__ import annotations

from _sim import parser, port_or_simulator

import motorbus


async def main(port: str) -> None:
    transport = motorbus.open_transport(port, baudrate=921600)
    async with motorbus.Bus(transport, families=[motorbus.Family.LA]) as bus:
        actuator = motorbus.InspireLA(bus, 1)
        status = await actuator.status()
        print(f"position {status.position}, {status.temperature} C, errors {status.errors!r}")
        await actuator.enable()
        moved = await actuator.move_to(1500)  # 0..2000 = 0..100 % of the stroke
        print(f"target now {moved.target}")
        await actuator.set_over_current_limit(1000)  # mA, 300..1500
        print(f"over-current limit {await actuator.over_current_limit()} mA")
        print(f"bus stats: {bus.stats.requests} requests, {bus.stats.timeouts} timeouts")


if __name__ == "__main__":
    args = parser(__doc__).parse_args()
    with port_or_simulator(args, ["la:1"], 921600) as port:
        motorbus.run(main(port))
