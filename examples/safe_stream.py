"""Stream a sine to LA actuators at 100 Hz from a BusManager; Ctrl-C stops them safely.

    python examples/safe_stream.py --port /dev/ttyUSB0 --ids 1-15 --safe-action pause

Runs until ``--seconds``, Ctrl-C (once or more), SIGTERM or SIGHUP.  Either way, leaving
``async with BusManager`` ends the stream and then pauses (or e-stops) every actuator
before the port closes, and the program prints "stopped safely" if every actuator
confirmed its stop; otherwise it lists those that did not and exits with status 1.
After a safe stop it exits as the command line does (docs/cli.md, exit codes): 0 at the
end of ``--seconds``; 128 + the signal number when a signal ended it - 130 for Ctrl-C,
143 for SIGTERM, 129 for SIGHUP - so that a shell, systemd or a supervisor sees that
it was stopped, not that it finished.  With
``--fail-after S`` the program raises an error S seconds into the stream, to show that
an exception in your code gets the same safe stop (and still ends the program with
its traceback, status 1).
"""

from __future__ import annotations

import asyncio
import math

from _sim import parser, port_or_simulator

import motorbus
from motorbus.protocol import la

#: 100 Hz: the fastest follow-mode rate the LA manual allows (3.5.3: 10-50 ms).
PERIOD_S = 0.010
#: The sine: centre, amplitude (positions 0..2000) and frequency (Hz).
CENTRE, AMPLITUDE, FREQUENCY_HZ = 1000, 400, 0.5


#: The manager of the run, to read its safe-stop report after main() ends (even by Ctrl-C).
MANAGERS: list[motorbus.BusManager] = []


async def main(
    port: str,
    baud: int,
    ids: str,
    safe_action: str,
    seconds: float | None,
    fail_after: float | None,
) -> None:
    manager = motorbus.BusManager()
    MANAGERS.append(manager)
    manager.add_bus("arm", port, baud=baud, devices=[f"la:{ids}"], la_safe_action=safe_action)
    async with manager:
        ids_on_bus = manager.specs["arm"].devices[0].ids
        actuators = [manager.la("arm", i) for i in ids_on_bus]
        for actuator in actuators:
            await actuator.enable()

        first_tick_sent = asyncio.Event()

        def targets(t: float, statuses: dict[int, la.Status]) -> list[float]:
            # Called once per tick, before the tick's frame is sent: the second call
            # means the first broadcast is out.
            if t > 0:
                first_tick_sent.set()
            phase = 2 * math.pi * FREQUENCY_HZ * t
            return [CENTRE + AMPLITUDE * math.sin(phase + i / 3) for i in range(len(actuators))]

        # Broadcast without feedback: one 0xF3 frame a tick carries all 15 targets.
        stream = manager.streamer("arm").follow(actuators, targets, period=PERIOD_S)
        await first_tick_sent.wait()
        print("streaming", flush=True)
        if fail_after is not None:
            await asyncio.sleep(fail_after)
            raise RuntimeError(f"your code failed {fail_after} s into the stream")
        if seconds is None:
            await stream.wait()  # a callable source never ends: runs until Ctrl-C
        else:
            await asyncio.sleep(seconds)
    # Here every actuator has been paused or e-stopped, and the port is closed.


if __name__ == "__main__":
    p = parser(__doc__)
    p.add_argument("--baud", type=int, default=921600, help="bits per second (921600)")
    p.add_argument("--ids", default="1-15", help="actuator IDs: 1-15 or 1,4,7 (1-15)")
    p.add_argument("--seconds", type=float, help="stop after this long (default: Ctrl-C)")
    p.add_argument("--safe-action", choices=["pause", "estop"], default="pause")
    p.add_argument("--fail-after", type=float, help="raise an error this long into the stream")
    args = p.parse_args()
    status = 0
    with port_or_simulator(args, [f"la:{args.ids}"], args.baud) as port:
        try:
            # motorbus.run: asyncio.run that turns SIGINT, SIGTERM and SIGHUP into the
            # same safe stop (a second Ctrl-C waits for it), then exits 128 + signal.
            motorbus.run(
                main(port, args.baud, args.ids, args.safe_action, args.seconds, args.fail_after)
            )
        except SystemExit as ended:
            # A signal ended main(): BusManager's exit ran the safe stop before this.
            status = ended.code if isinstance(ended.code, int) else 1
            print(f"interrupted (status {status})", flush=True)
    report = MANAGERS[0].stop_report if MANAGERS else None
    if report is None or not report.ok:
        # A stop that did not complete outranks how the program was ended.
        print(report if report is not None else "safe stop did not run", flush=True)
        raise SystemExit(1)
    print("stopped safely", flush=True)
    raise SystemExit(status)
