"""Bounded waits for tests: a condition that never comes true fails with a message
naming it, instead of hanging until pytest-timeout kills the whole run."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

#: Longest a test waits for a condition (generous: CI machines are shared and slow).
EVENTUALLY_TIMEOUT_S = 10.0


async def eventually(
    condition: Callable[[], object],
    what: str,
    *,
    timeout: float = EVENTUALLY_TIMEOUT_S,
    poll: float = 0.002,
) -> None:
    """Wait until ``condition()`` is true, polling every ``poll`` seconds.

    Raises:
        AssertionError: not true within ``timeout`` seconds; the message says ``what``
            was awaited.
    """
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"waited {timeout:g} s for {what}; it never happened")
        await asyncio.sleep(poll)
