"""Shared fixtures; the shared helpers live in ``tests.helpers`` (``sim_bus`` fails a
test whose bus leaves tasks running behind it; ``PACINGS``)."""

from __future__ import annotations

import gc
from collections.abc import Callable
from typing import Any

import pytest

from tests.helpers import PACINGS as PACINGS
from tests.helpers import sim_bus as sim_bus


@pytest.fixture
def make_sim_bus() -> Callable[..., Any]:
    return sim_bus


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze what collection built: full garbage collections over the suite's large heap
    took 60-137 ms, long enough to turn an on-time reply into a late one (the bus decides
    lateness by time, as it must)."""
    gc.collect()
    gc.freeze()
