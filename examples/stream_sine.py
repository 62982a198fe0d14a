"""Stream a sine to 15 actuators at 100 Hz (one 0xF3 broadcast a tick), polling status."""

from __future__ import annotations

import math

from _sim import parser, port_or_simulator

import motorbus
from motorbus.protocol import la


async def main(port: str, seconds: float) -> None:
    transport = motorbus.open_transport(port, baudrate=921600)
    async with motorbus.Bus(transport, families=[motorbus.Family.LA]) as bus:
        actuators = [motorbus.InspireLA(bus, i) for i in range(1, 16)]
        for a in actuators:
            await a.enable()

        def targets(t: float, statuses: dict[int, la.Status]) -> list[float] | None:
            if t >= seconds:
                return None  # ends the stream
            return [1000 + 500 * math.sin(2 * math.pi * 0.5 * t + i / 3) for i in range(15)]

        streamer = motorbus.Streamer(bus)
        async with streamer.follow(
            actuators, targets, period=0.01, poll_status=True, safe_action="pause"
        ) as stream:
            await stream.wait()
        print(stream.stats.summary())
        print({i: s.position for i, s in sorted(stream.statuses.items())})


if __name__ == "__main__":
    p = parser(__doc__)
    p.add_argument("--seconds", type=float, default=3.0)
    args = p.parse_args()
    with port_or_simulator(args, ["la:1-15"], 921600) as port:
        motorbus.run(main(port, args.seconds))
