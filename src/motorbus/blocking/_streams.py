"""Blocking streams: ``Streamer.follow`` without ``await``, and targets from your thread.

The stream runs on the bus's own thread, on the same absolute tick deadlines as in an
asyncio program; the calling thread only starts, steers and stops it.  A
:class:`Setpoint` is the way to feed it from a plain loop: ``setpoint.set(targets)``
from the calling thread, and each tick sends the latest targets set (a tick never
waits for the caller; a caller slower than the period repeats its last targets).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

from motorbus import streams as _streams
from motorbus.blocking._devices import InspireLA
from motorbus.blocking._proxy import Proxy
from motorbus.errors import LocalProtocolError
from motorbus.streaming.targets import TargetAdapter

if TYPE_CHECKING:
    from motorbus.blocking._bus import BusView
    from motorbus.devices import la as _la
    from motorbus.protocol import la

__all__ = ["Setpoint", "Stream", "Streamer"]


class Setpoint:
    """Targets that the calling thread sets and a stream sends, the latest each tick.

    ``Setpoint(initial)`` holds ``initial`` (a position for one actuator, one position
    per actuator in the stream's order, or ``{id: position}``); give it to
    ``Streamer.follow`` as the targets.  ``set`` replaces them, checked at once against
    the stream's actuators (``LocalProtocolError`` names the field and the range, and
    the stream keeps its previous targets); ``end`` ends the stream at its next tick,
    with its safe action.  Thread-safe; it works with the asyncio ``Streamer`` as well.
    """

    def __init__(self, initial: object) -> None:
        self._lock = threading.Lock()
        self._item: object = initial
        self._adapter: TargetAdapter | None = None
        self._ended = False

    def set(self, targets: object) -> None:
        """Send ``targets`` from the next tick on.

        Raises:
            LocalProtocolError: a target out of 0..2000, of the wrong kind or naming an
                actuator the stream does not drive; or the setpoint has ended.
        """
        adapter = self._adapter
        checked: object = targets if adapter is None else adapter.normalise(targets)
        with self._lock:
            if self._ended:
                raise LocalProtocolError(
                    "this setpoint has ended: start a new stream", field="targets"
                )
            self._item = checked

    def end(self) -> None:
        """End the stream at its next tick (it applies its safe action)."""
        with self._lock:
            self._ended = True

    @property
    def ended(self) -> bool:
        """True once :meth:`end` was called."""
        return self._ended

    @property
    def targets(self) -> object:
        """The targets sent at each tick now."""
        return self._item

    def __call__(self, t: float, statuses: Mapping[int, la.Status]) -> object:
        with self._lock:
            return None if self._ended else self._item

    def bind(self, ids: Sequence[int]) -> None:
        """Check the targets against a stream's actuators from now on (``follow`` calls it).

        Raises:
            LocalProtocolError: the targets held now do not fit these actuators.
        """
        adapter = TargetAdapter(ids, self)
        checked = adapter.normalise(self._item)
        with self._lock:
            self._adapter = adapter
            self._item = checked


class Streamer(Proxy[_streams.Streamer]):
    """Serves the streams of one blocking bus: :class:`motorbus.Streamer` without ``await``.

    Args:
        bus: an open :class:`motorbus.blocking.Bus` carrying LA actuators, or a
            served one (``motorbus.blocking.connect(...).bus()``).
        phase: offset of this bus's tick grid in seconds.
        lead: a served bus's streams only: how far ahead of their ticks the targets go
            to the server (as :class:`motorbus.Streamer`).
    """

    _bus: BusView[Any]

    def __init__(self, bus: BusView[Any], *, phase: float = 0.0, lead: float | None = None) -> None:
        self._runner = bus._runner
        self._aio = self._runner.call_sync(
            lambda: _streams.Streamer(bus._any, phase=phase, lead=lead)
        )
        self._bus = bus

    @classmethod
    def _on(cls, bus: BusView[Any], aio: _streams.Streamer) -> Streamer:
        proxy = cls._of(aio, bus._runner)
        proxy._bus = bus
        return proxy

    def follow(
        self,
        actuators: InspireLA | Sequence[InspireLA],
        targets: object,
        **options: Any,
    ) -> Stream:
        """Start streaming follow-mode targets; returns the running :class:`Stream`.

        ``targets`` and ``options`` (``period``, ``feedback``, ``poll_status``,
        ``safe_action``, ``on_gap``, ``max_speed``, ``max_missed``) are those of
        :meth:`motorbus.Streamer.follow`.  Give a :class:`Setpoint` to set the targets
        from this thread; a callable or an iterator runs on the bus's thread, at each
        tick, so it must return at once (and must not make blocking motorbus calls).

        Raises:
            LocalProtocolError: as ``motorbus.Streamer.follow``; nothing is sent.
        """
        group = [actuators] if isinstance(actuators, InspireLA) else list(actuators)
        aio_group: list[_la.InspireLA] = []
        for a in group:
            if not isinstance(a, InspireLA):
                raise LocalProtocolError(
                    f"actuators must be motorbus.blocking.InspireLA, got {a!r}",
                    field="actuators",
                )
            aio_group.append(a.aio)
        if isinstance(targets, Setpoint):
            targets.bind([a.id for a in group])

        def start() -> _streams.Stream:
            return self._aio.follow(aio_group, targets, **options)

        return Stream._of(self._runner.call_sync(start), self._runner)

    def close(self, *, hold: bool = False) -> None:
        """End every stream with its safe action (none with ``hold``); see
        :meth:`motorbus.Streamer.close`.  Ctrl-C waits for it to finish."""
        self._runner.finish(self._aio.close(hold=hold))


class Stream(Proxy[_streams.Stream]):
    """A running (or finished) stream: :class:`motorbus.Stream` without ``await``.

    As a context manager, leaving the block stops it with its safe action, however
    the block is left.
    """

    @property
    def ids(self) -> tuple[int, ...]:
        """The actuators' IDs, in order."""
        return self._aio.ids

    @property
    def period(self) -> float:
        """Seconds between ticks."""
        return self._aio.period

    @property
    def done(self) -> bool:
        """True once the stream has ended."""
        return self._aio.done

    @property
    def error(self) -> BaseException | None:
        """What ended the stream, if an error did."""
        return self._aio.error

    @property
    def statuses(self) -> dict[int, la.Status]:
        """A copy of the latest status of each actuator (feedback replies and polls)."""
        return self._runner.call_sync(dict, self._aio.statuses)

    @property
    def last_targets(self) -> dict[int, int]:
        """A copy of the targets last sent, by ID."""
        return self._runner.call_sync(dict, self._aio.last_targets)

    @property
    def stats(self) -> Any:
        """The stream's counters (``motorbus.Stream.stats``)."""
        return self._aio.stats

    def wait(self) -> None:
        """Wait until the stream ends.

        Raises:
            StreamEnded: it ended on an error.
        """
        self._runner.call(self._aio.wait())

    def stop(self, *, hold: bool = False) -> None:
        """End the stream and apply its safe action (none with ``hold``); idempotent.
        Ctrl-C waits for the safe action to go out."""
        self._runner.finish(self._aio.stop(hold=hold))

    def pause(self) -> None:
        """Stop sending targets (the tick grid keeps running)."""
        self._runner.call_sync(self._aio.pause)

    def resume(self) -> None:
        """Send targets again from the next tick."""
        self._runner.call_sync(self._aio.resume)

    def set_targets(self, source: object) -> None:
        """Replace the target source (see :meth:`motorbus.Stream.set_targets`)."""
        if isinstance(source, Setpoint):
            source.bind(self.ids)
        self._runner.call_sync(self._aio.set_targets, source)

    def __enter__(self) -> Stream:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
