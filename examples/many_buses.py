"""Several buses from one TOML file: stream on one, poll another; safe stop on the way out."""

from __future__ import annotations

import argparse
import contextlib
import tempfile
from pathlib import Path

import motorbus
from motorbus.sim.process import SimProcess

BUSES_TOML = """
[[bus]]
name = "left-arm"
url = "{left}"
baud = 921600
la_safe_action = "pause"
devices = ["la:1-4"]

[[bus]]
name = "right-arm"
url = "{right}"
baud = 921600
devices = ["la:1-4"]
"""


async def main(bus_file: Path) -> None:
    async with motorbus.BusManager.from_toml(bus_file) as mgr:
        left = [mgr.la("left-arm", i) for i in range(1, 5)]
        stream = mgr.streamer("left-arm").follow(
            left, lambda t, s: None if t > 1 else [800, 900, 1000, 1100], period=0.02
        )
        for i in range(1, 5):
            status = await mgr.la("right-arm", i).status()
            print(f"right-arm la:{i} at {status.position}")
        await stream.wait()
        s = stream.stats  # a tick a loaded host started over a period late is skipped
        print(f"left-arm: {s.ticks} ticks, {s.skipped} skipped, {s.late} late")
    # Leaving the block paused every actuator of every bus before closing the ports.


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("bus_file", nargs="?", help="a TOML bus file (default: two simulators)")
    args = p.parse_args()
    with contextlib.ExitStack() as stack:
        if args.bus_file:
            path = Path(args.bus_file)
        else:
            left = stack.enter_context(SimProcess(["la:1-4"], baud=921600))
            right = stack.enter_context(SimProcess(["la:1-4"], baud=921600))
            path = Path(stack.enter_context(tempfile.TemporaryDirectory())) / "buses.toml"
            path.write_text(BUSES_TOML.format(left=left.path, right=right.path), encoding="utf-8")
        motorbus.run(main(path))
