"""Target sources: what a stream's source yields, made into ``{id: position}``.

Pure (no asyncio, no clock): the stream's tick loop fetches an item from the source
(awaiting it if need be) and hands it here.  Also the ramp that brings a stream back
to its trajectory after a gap.
"""

from __future__ import annotations

import inspect
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator, Mapping, Sequence
from typing import Any, TypeAlias

from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.validation import CheckedRows, is_scalar, target_id, target_position

__all__ = ["EXHAUSTED", "Pending", "TargetAdapter", "TargetSource", "Targets", "ramp_step"]

Targets: TypeAlias = Mapping[int, int]
TargetSource: TypeAlias = Any  # sequence, iterator, async iterator or callable; see Stream

#: What ``TargetAdapter.next_item`` returns when a sequence or iterator has run out.
EXHAUSTED: Any = object()
#: Exactly these types (not bool, not a numpy scalar) take the fast path of ``_values``.
_PLAIN_NUMBERS = frozenset((int, float))
#: What a function source returns on every tick, and never awaitable: no awaitable check
#: (``inspect.isawaitable`` is six calls a tick, an ABC check among them).
_PLAIN_ITEMS = frozenset((list, tuple, dict, int, float, type(None)))


class Pending:
    """Targets still to be awaited: an async iterator's next item, or the awaitable a
    target function returned (``TargetAdapter.fetch``; ``finish`` awaits it)."""

    __slots__ = ("awaitable",)

    def __init__(self, awaitable: Awaitable[Any]) -> None:
        self.awaitable = awaitable


class TargetAdapter:
    """One stream's target source and the actuators it drives (``ids``, in order).

    Exactly one of ``sequence``, ``iterator``, ``aiterator`` and ``function`` is set,
    by the kind of source (see ``motorbus.streams.Stream``).
    """

    def __init__(self, ids: Sequence[int], source: TargetSource) -> None:
        self.ids = tuple(ids)
        self.sequence: Sequence[Any] | None = None
        self.iterator: Iterator[Any] | None = None
        self.aiterator: AsyncIterator[Any] | None = None
        self.function: Callable[..., Any] | None = None
        self.bind(source)

    def bind(self, source: TargetSource) -> None:
        """Take a new source; raises ``LocalProtocolError`` for one of no known kind."""
        if isinstance(source, (str, bytes, bytearray)):
            # Strings are sequences: "1500" would stream the targets 1, 5, 0, 0.
            raise LocalProtocolError(
                f"targets must be positions, not text: got {source!r}", field="targets"
            )
        sequence = iterator = aiterator = function = None
        if isinstance(source, Sequence):
            sequence = source
        elif hasattr(source, "__len__") and hasattr(source, "__getitem__"):
            sequence = source  # numpy arrays and the like
        elif hasattr(source, "__anext__"):
            aiterator = source
        elif hasattr(source, "__next__") or (hasattr(source, "__iter__") and not callable(source)):
            iterator = iter(source)
        elif callable(source):
            function = source
        else:
            raise LocalProtocolError(
                f"targets must be a sequence, an iterator, an async iterator or a callable "
                f"f(t, statuses); got {type(source).__name__}",
                field="targets",
            )
        if sequence is not None:
            self.check_rows(sequence)
        #: The highest index of the sequence handed out (``next_item``).
        self.last_index = -1
        self.sequence, self.iterator, self.aiterator, self.function = (
            sequence,
            iterator,
            aiterator,
            function,
        )

    def check_rows(self, rows: Sequence[Any]) -> None:
        """Check every row of a list, a tuple or an array now, so that a bad one refuses
        the stream before anything of it is sent (they are all there at ``follow``).  A
        numpy array of numbers is checked in C (its minimum and maximum); a list row by
        row, in Python.  An iterator, a function, and a sequence of another
        kind (one that computes its rows on access, perhaps 10**9 of them) are checked
        item by item, at their tick.

        Raises:
            LocalProtocolError: a row that ``normalise`` refuses, named by its index
                (``targets row INDEX``) with the reason.
        """
        if type(rows) is CheckedRows or self._numbers_in_range(rows):
            return
        held = isinstance(rows, list | tuple) or hasattr(rows, "dtype") or hasattr(rows, "dtypes")
        if not held:
            return  # rows computed on access, as many as it likes: checked at each tick
        try:
            count = len(rows)
        except TypeError:  # a 0-d numpy array: __len__ is there, and refuses
            raise LocalProtocolError(
                f"targets must be rows (one a tick), got a {type(rows).__name__} without a "
                "length; nothing sent",
                field="targets",
                value=rows,
            ) from None
        for index in range(count):
            try:
                item = rows[index]
            except Exception as err:  # a table indexed by label (pandas), say
                raise LocalProtocolError(
                    f"targets row {index} (of {count}) could not be read ({type(err).__name__}: "
                    f"{err}): give rows as a list or a 2-D numpy array; nothing sent",
                    field="targets",
                    value=type(rows).__name__,
                ) from err
            if item is None:
                return  # the stream ends here: the rows after it are never sent
            try:
                self.normalise(item)
            except LocalProtocolError as err:
                raise LocalProtocolError(
                    f"targets row {index} (of {count}): {err}; nothing sent",
                    field=err.field,
                    value=err.value,
                ) from None

    def _numbers_in_range(self, rows: Any) -> bool:
        """True for a numpy array of numbers shaped for ``ids`` with every value in range
        (any doubt, a NaN among them, goes to the row-by-row check for its message)."""
        ndim = getattr(rows, "ndim", None)
        if getattr(getattr(rows, "dtype", None), "kind", None) not in ("i", "u", "f"):
            return False
        shaped = (ndim == 1 and len(self.ids) == 1) or (
            ndim == 2 and tuple(rows.shape)[1:] == (len(self.ids),)
        )
        if not shaped or not len(rows):
            return False
        return bool(rows.min() >= la.POSITION_MIN and rows.max() <= la.POSITION_MAX)

    def fetch(self, t: float, statuses: Mapping[int, Any], index: int) -> Targets | Pending | None:
        """The targets at time ``t`` (a callable's argument, with ``statuses``), or the
        ``index``-th item of a sequence or iterator; None at the end; a ``Pending`` when
        they must be awaited (an async iterator's next item, an awaitable a function
        returned: ``finish`` it).  Never awaits, so a tick of plain sources needs no
        task turn."""
        item: Any
        if self.aiterator is not None:
            return Pending(self.aiterator.__anext__())
        if self.function is not None:
            item = self.function(t, statuses)
            if type(item) not in _PLAIN_ITEMS and inspect.isawaitable(item):
                return Pending(item)
        else:
            item = self.next_item(index)
        if item is None or item is EXHAUSTED:
            return None
        return self.normalise(item)

    async def finish(self, pending: Pending) -> Targets | None:
        """The targets ``fetch`` left pending, awaited; None at the end."""
        try:
            item = await pending.awaitable
        except StopAsyncIteration:
            if self.aiterator is None:
                raise  # from a target function: a failure, not the end
            return None
        if item is None or item is EXHAUSTED:
            return None
        return self.normalise(item)

    async def next(self, t: float, statuses: Mapping[int, Any], index: int) -> Targets | None:
        """``fetch``, awaited where it must be: a served stream's client takes its
        targets here (a local stream's tick loop calls ``fetch``)."""
        targets = self.fetch(t, statuses, index)
        if isinstance(targets, Pending):
            return await self.finish(targets)
        return targets

    def next_item(self, index: int) -> Any:
        """Item ``index`` of a sequence, or the next of an iterator; ``EXHAUSTED`` at
        the end.  (Async iterators and functions are called by the tick loop.)"""
        rows = self.sequence
        if rows is not None:
            if index < len(rows):
                self.last_index = index
                return rows[index]
            last = len(rows) - 1
            if self.last_index < last:
                # Ticks skipped past the end (a late start, a loaded host): the last row
                # is where the trajectory ends, so it still goes out, once.
                self.last_index = last
                return rows[last]
            return EXHAUSTED
        assert self.iterator is not None
        return next(self.iterator, EXHAUSTED)

    def normalise(self, item: Any) -> Targets:
        """``item`` as ``{id: position}``: a position for a single actuator, one per
        actuator in ``ids`` order, or a mapping naming some of them."""
        kind = type(item)
        if kind is list or kind is tuple:  # the common case first: no ABC checks
            return self._values(item)
        if kind is float or kind is int:
            return self._scalar(item)
        if isinstance(item, Mapping):
            targets = {target_id(i): target_position(v, f"targets[{i}]") for i, v in item.items()}
            unknown = set(targets) - set(self.ids)
            if unknown:
                raise LocalProtocolError(
                    f"targets name ids {sorted(unknown)} that this stream does not drive "
                    f"(it drives {list(self.ids)})",
                    field="targets",
                )
            return targets
        if isinstance(item, (int, float)) or is_scalar(item):
            return self._scalar(item)
        if isinstance(item, str | bytes):  # a sequence, but of characters
            raise LocalProtocolError(
                f"targets must be positions, not text: got {item!r}", field="targets"
            )
        # A numpy row (a 1-D array, or a row of a 2-D array of ticks x actuators):
        # tolist() gives plain floats/ints, which take the fast path below.
        tolist = getattr(item, "tolist", None)
        values = tolist() if callable(tolist) else list(item)
        return self._values(values)

    def _scalar(self, item: Any) -> Targets:
        if len(self.ids) != 1:
            raise LocalProtocolError(
                f"a single target was given for {len(self.ids)} actuators; give one "
                "per actuator or a mapping {id: position}",
                field="targets",
            )
        return {self.ids[0]: target_position(item, "target")}

    def _values(self, values: Sequence[Any]) -> Targets:
        if len(values) != len(self.ids):
            raise LocalProtocolError(
                f"targets has {len(values)} values for {len(self.ids)} actuators",
                field="targets",
            )
        # The common case, once a tick per bus: plain numbers all in range.  Anything
        # else (a bool, NaN, a string, out of range) takes the checking path below,
        # which names the offending value.
        # (map, no generator: one call, not one a value; issue 40 counts the calls.)
        if _PLAIN_NUMBERS.issuperset(map(type, values)):
            try:
                if min(values) >= la.POSITION_MIN and max(values) <= la.POSITION_MAX:
                    return dict(zip(self.ids, map(round, values), strict=True))
            except (ValueError, OverflowError):  # NaN or infinity: round() refuses them
                pass
        return {
            i: target_position(v, f"targets[{i}]") for i, v in zip(self.ids, values, strict=True)
        }


def ramp_step(ramp: dict[int, float], targets: Targets, step: float) -> dict[int, int]:
    """One tick of the ramp after a gap: move each ramping actuator at most ``step``
    from where it was last sent (``ramp``) toward its target.

    ``ramp`` is updated in place; an actuator that reaches its target leaves it (from
    then on it follows the targets as they come).  Actuators not ramping pass through.
    """
    out = dict(targets)
    for ident, goal in targets.items():
        at = ramp.get(ident)
        if at is None:
            continue
        if abs(goal - at) <= step:
            del ramp[ident]
            continue
        at += step if goal > at else -step
        ramp[ident] = at
        out[ident] = round(at)
    return out
