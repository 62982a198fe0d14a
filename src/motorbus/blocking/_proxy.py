"""Blocking methods made from the asyncio ones, with their signatures and docstrings.

``status = coroutine(InspireLA.status)`` in a proxy class gives a method that takes
the asyncio method's arguments (checked by mypy through ``ParamSpec``), runs it on the
background loop and returns what it returns; its docstring and signature are the
asyncio method's (``help()``, IDEs and the API reference show them).  ``wrapped``
does the same for a method that returns an asyncio object (an ``InspireLA``), and
hands back its blocking proxy; ``plain`` forwards a method that does no I/O.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Coroutine
from typing import Any, Concatenate, Generic, ParamSpec, Self, TypeVar

from motorbus.blocking._runner import Runner

__all__ = ["Proxy", "coroutine", "plain", "wrapped"]

P = ParamSpec("P")
R = TypeVar("R")
W = TypeVar("W")
T = TypeVar("T")


class Proxy(Generic[T]):
    """A blocking view of one asyncio object ``aio`` living on the background loop."""

    _aio: T
    _runner: Runner

    @classmethod
    def _of(cls, aio: T, runner: Runner) -> Self:
        proxy = cls.__new__(cls)
        proxy._aio = aio
        proxy._runner = runner
        return proxy

    @property
    def aio(self) -> T:
        """The asyncio object behind this one (use it only from the asyncio API's side,
        e.g. inside a target callback, which runs on the bus's own thread)."""
        return self._aio

    def __repr__(self) -> str:
        return f"blocking {self._aio!r}"


class Closing:
    """A context manager whose exit calls ``close()``, however the block is left."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def coroutine(
    method: Callable[Concatenate[T, P], Coroutine[Any, Any, R]],
) -> Callable[Concatenate[Proxy[T], P], R]:
    """A blocking method that runs the asyncio ``method`` and returns its result."""

    @functools.wraps(method)
    def call(self: Proxy[T], /, *args: P.args, **kwargs: P.kwargs) -> R:
        return self._runner.call(method(self._aio, *args, **kwargs))

    return call


def wrapped(
    method: Callable[Concatenate[T, P], Coroutine[Any, Any, R]],
    wrap: Callable[[Proxy[T], R], W],
) -> Callable[Concatenate[Proxy[T], P], W]:
    """As :func:`coroutine`, the result handed to ``wrap(self, result)`` (its proxy)."""

    @functools.wraps(method)
    def call(self: Proxy[T], /, *args: P.args, **kwargs: P.kwargs) -> W:
        return wrap(self, self._runner.call(method(self._aio, *args, **kwargs)))

    return call


def plain(method: Callable[Concatenate[T, P], R]) -> Callable[Concatenate[Proxy[T], P], R]:
    """A method that does no I/O and touches nothing of the loop, called in place."""

    @functools.wraps(method)
    def call(self: Proxy[T], /, *args: P.args, **kwargs: P.kwargs) -> R:
        return method(self._aio, *args, **kwargs)

    return call
