"""A host-side recorder for transport tests: collects bytes and losses, awaits them."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

WAIT_S = 5.0  # generous bound on awaiting bytes a pty, loopback or call_soon delivers


class Recorder:
    """Pass ``on_data`` / ``on_lost`` to ``Transport.open``; await what arrives, never sleep."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []
        self.lost: list[BaseException | None] = []
        self._changed = asyncio.Event()

    def on_data(self, data: bytes) -> None:
        assert data, "on_data must never be called with empty bytes"
        self.chunks.append(data)
        self._changed.set()

    def on_lost(self, exc: BaseException | None) -> None:
        self.lost.append(exc)
        self._changed.set()

    @property
    def received(self) -> bytes:
        return b"".join(self.chunks)

    async def wait_for(self, done: Callable[[], object]) -> None:
        """Return once ``done()`` is true, re-checking after every callback."""

        async def loop() -> None:
            while not done():
                self._changed.clear()
                await self._changed.wait()

        await asyncio.wait_for(loop(), WAIT_S)
