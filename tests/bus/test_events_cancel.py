"""``Subscription.next`` under cancellation: a cancelled waiter must end cancelled.

Found while running the project stepper against a controller that sends ``EE DD`` after a
stop (tests/devices/test_project_stepper_device.py): ``ProjectStepper.run_project`` cancels
its ``sub.next`` task and leaves the ``with subscribe`` block in the same loop iteration.
On Python 3.11 ``asyncio.wait_for`` returned the inner result instead of raising when the
inner future was already done at the moment the cancel landed, so ``next`` looped, found the
subscription closed and ended with ``StopAsyncIteration``: the cancel was lost and the task
ended with an exception nobody retrieved ("Task exception was never retrieved").
``next`` now waits with ``asyncio.timeout``, which keeps the cancel.
"""

from __future__ import annotations

import asyncio

import pytest

from motorbus.bus.events import EventHub, ProjectFinished


async def test_cancel_and_close_in_one_iteration_ends_the_waiter_cancelled() -> None:
    hub = EventHub()
    sub = hub.subscribe(ProjectFinished)
    waiter = asyncio.ensure_future(sub.next(timeout=5.0))
    await asyncio.sleep(0)  # the waiter is now parked in next()
    await asyncio.sleep(0)
    waiter.cancel()
    sub.close()
    done, _ = await asyncio.wait({waiter}, timeout=5.0)
    assert waiter in done
    if not waiter.cancelled():
        # Retrieve it (no "never retrieved" noise), then fail with what it ended with.
        exc = waiter.exception()
        pytest.fail(f"the cancelled waiter ended with {exc!r}", pytrace=False)


async def test_close_alone_ends_the_waiter_with_stop_async_iteration() -> None:
    hub = EventHub()
    sub = hub.subscribe(ProjectFinished)
    waiter = asyncio.ensure_future(sub.next(timeout=5.0))
    await asyncio.sleep(0)
    sub.close()
    with pytest.raises(StopAsyncIteration):
        await asyncio.wait_for(waiter, 5.0)
