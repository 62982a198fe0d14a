"""A transport that shows what passes through it, both ways, then hands it on.

``motorbus replay --to`` wraps the port's transport in a :class:`Tee` so that it can print
every frame the bus writes and every byte that comes back, without the bus knowing.
"""

from __future__ import annotations

from collections.abc import Callable

from motorbus import DataCallback, LostCallback, Transport, TransportStats

__all__ = ["Tee"]


class Tee(Transport):
    """Wraps ``inner``: ``on_sent`` sees each write, ``on_received`` each chunk read.

    Args:
        inner: the transport that does the I/O.
        on_sent: called with the bytes of each write, after ``inner`` took them.
        on_received: called with each chunk read, before the bus sees it.
    """

    def __init__(
        self,
        inner: Transport,
        on_sent: Callable[[bytes], None],
        on_received: Callable[[bytes], None],
    ) -> None:
        self.inner = inner
        self.url = inner.url
        self.baudrate = inner.baudrate
        self._on_sent = on_sent
        self._on_received = on_received

    @property
    def stats(self) -> TransportStats:  # type: ignore[override]
        return self.inner.stats

    async def open(self, on_data: DataCallback, on_lost: LostCallback) -> None:
        def data(chunk: bytes) -> None:
            self._on_received(chunk)
            on_data(chunk)

        await self.inner.open(data, on_lost)

    def write(self, data: bytes) -> None:
        self.inner.write(data)
        self._on_sent(bytes(data))

    def drain_input(self) -> None:
        self.inner.drain_input()

    async def close(self) -> None:
        await self.inner.close()

    @property
    def is_open(self) -> bool:
        return self.inner.is_open
