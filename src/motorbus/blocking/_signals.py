"""SIGTERM and SIGHUP in a blocking program: stop the motion first, then end as the
signal would.

An asyncio program gets this from motorbus while a bus is open
(``motorbus.runtime.shutdown``); a blocking program's loop runs on a thread of its own, where
Python delivers no signals, so the first blocking bus opened from the main thread
installs these handlers there, for the signals whose disposition is still the default
(a program's own handlers are left alone; ``MOTORBUS_SIGNALS=0`` leaves every signal
alone).  Ctrl-C needs none: Python raises ``KeyboardInterrupt`` in the main thread, and
the blocking calls and ``with`` blocks stop safely on it.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable

__all__ = ["protect"]

log = logging.getLogger("motorbus.blocking")

#: The signals handled here (those this platform has: Windows has no SIGHUP).
SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name)
)

_installed: set[signal.Signals] = set()
_stopping = False


def _enabled() -> bool:
    # The same switch as motorbus.runtime.shutdown's: MOTORBUS_SIGNALS=0 keeps motorbus away.
    return os.environ.get("MOTORBUS_SIGNALS", "1").strip() not in ("0", "off", "no", "false")


def protect(stop_everything: Callable[[], None]) -> None:
    """Install the handlers (once, from the main thread only, where still default)."""
    if not _enabled() or threading.current_thread() is not threading.main_thread():
        return
    for sig in SIGNALS:
        if sig in _installed or signal.getsignal(sig) is not signal.SIG_DFL:
            continue
        signal.signal(sig, _handler(stop_everything))
        _installed.add(sig)


def _handler(stop_everything: Callable[[], None]) -> Callable[[int, object], None]:
    def on_signal(signum: int, frame: object) -> None:
        global _stopping
        name = signal.Signals(signum).name
        if _stopping:
            log.warning("%s again: still stopping the motion safely", name)
            return
        _stopping = True
        log.warning("%s: stopping the motion safely before exiting", name)
        try:
            stop_everything()
        finally:
            signal.signal(signum, signal.SIG_DFL)
            signal.raise_signal(signum)  # end as the signal would have, now that it is safe

    return on_signal
