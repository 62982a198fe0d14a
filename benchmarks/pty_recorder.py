"""A receiving end for many ptys at once: records when each frame arrived, nothing more.

``python benchmarks/pty_recorder.py N OUT.json`` opens N pseudo-terminals, prints
their device paths (one line, space-separated), and records the ``time.monotonic()``
at which each complete LA request frame arrived on each of them.  On SIGINT or
SIGTERM it writes ``{"frames": [[[t, cmd], ...] per pty]}`` to OUT.json and exits.

With ``--answer`` (``pty_recorder.py N OUT.json --answer``) it also answers every request
addressed to LA IDs 1-15 at once, from an ``LAModel`` per ID and pty (no wire-time
emulation): bench_cpu.py needs its status polls answered on many buses.

Why not the full simulator: bench_stream's scaling run drives up to 32 buses of 15
actuators, and 32 simulator processes need more CPU than this 2-core machine has
(about 7 % of a core each at 100 frames/s), so they would measure their own
starvation.  This one process, one ``select`` loop, only timestamps arrivals.
"""

from __future__ import annotations

import json
import os
import select
import signal
import sys
import time
import tty

from motorbus.protocol.base import Direction, Family
from motorbus.protocol.reassembler import Frame, Reassembler
from motorbus.sim.la import LAModel

#: LA IDs answered with ``--answer``.
ANSWERED_IDS = range(1, 16)


def main() -> int:
    count, out = int(sys.argv[1]), sys.argv[2]
    answer = "--answer" in sys.argv[3:]
    masters: list[int] = []
    slaves: list[int] = []
    paths: list[str] = []
    for _ in range(count):
        master, slave = os.openpty()
        tty.setraw(slave)
        masters.append(master)
        slaves.append(slave)  # kept open so reads never fail with EIO between clients
        paths.append(os.ttyname(slave))
    print(" ".join(paths), flush=True)
    index = {fd: i for i, fd in enumerate(masters)}
    reassemblers = [Reassembler(direction=Direction.REQUEST, families=[Family.LA]) for _ in masters]
    frames: list[list[tuple[float, int]]] = [[] for _ in masters]
    models = [{i: LAModel(i) for i in ANSWERED_IDS} if answer else {} for _ in masters]
    stop = False

    def on_signal(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    while not stop:
        try:
            ready, _, _ = select.select(masters, [], [], 0.2)
        except InterruptedError:
            continue
        now = time.monotonic()
        for fd in ready:
            try:
                data = os.read(fd, 4096)
            except OSError:
                continue
            i = index[fd]
            for item in reassemblers[i].feed(data):
                if type(item) is Frame:
                    frames[i].append((now, item.raw[4]))
                    model = models[i].get(item.raw[3])
                    if model is not None:
                        for reply in model.handle(bytes(item.raw), now):
                            os.write(fd, reply)
    with open(out, "w", encoding="utf-8") as fh:
        json.dump({"frames": frames}, fh)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
