"""Many simulated LA buses in one process, each on its own pty: for bench_serve_scale.

``python benchmarks/sim_many.py N [DEVICE_SPEC ...]`` starts N ``PtySim`` (the full
simulator: wire-time pacing at 921600 baud, turnarounds, the LA model), one thread
each, prints their device paths on one line (space-separated), then prints a line

    safe INDEX T HEX

for every safe-stop request frame (LA pause or e-stop) that bus INDEX received, T its
arrival in ``time.monotonic()`` seconds (the clock is the machine's, so the parent
compares it with its own).  SIGINT or SIGTERM ends it.

Why one process: 32 ``motorbus sim`` processes would each load an interpreter and
wake on their own; one process with a thread per pty is one interpreter, and each
pty still has a simulator of its own.
"""

from __future__ import annotations

import signal
import sys
import threading
from typing import Any

from motorbus.protocol import la
from motorbus.protocol.base import format_hex
from motorbus.sim.pty import PtySim
from motorbus.sim.spec import parse_device_specs

#: The safe-stop frames looked for, by their hex as the simulator logs it.
SAFE_ACTIONS = (la.ControlAction.PAUSE, la.ControlAction.ESTOP)


def safe_frames(ids: range) -> set[str]:
    return {format_hex(la.Control(i, a).encode()) for i in ids for a in SAFE_ACTIONS}


def main() -> int:
    count = int(sys.argv[1])
    specs = sys.argv[2:] or ["la:1"]
    safe = safe_frames(range(1, 255))
    out = threading.Lock()
    sims: list[PtySim] = []

    def watcher(index: int, sim: list[PtySim]) -> Any:
        def log(record: dict[str, Any]) -> None:
            if record["dir"] == "rx" and record["hex"] in safe:
                t = sim[0].bus.epoch + record["t"]
                with out:
                    sys.stdout.write(f"safe {index} {t:.6f} {record['hex'].replace(' ', '')}\n")
                    sys.stdout.flush()

        return log

    for i in range(count):
        holder: list[PtySim] = []
        sim = PtySim(parse_device_specs(specs), baud=921600, log=watcher(i, holder))
        holder.append(sim)
        sims.append(sim.start())
    print(" ".join(s.path for s in sims), flush=True)
    done = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: done.set())
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    while not done.wait(0.5):
        pass
    for sim in sims:
        sim.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
