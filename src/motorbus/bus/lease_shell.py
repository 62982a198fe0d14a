"""The bus's side of the leases: acquiring for an owner, the rule at submit, and the one
place that defines and sends safe actions (``motorbus.bus.leases`` is the pure table).

``Bus`` holds one ``LeaseKeeper`` (``bus.lease_keeper``) and calls it from two places:
``submit`` (``claim``, for every command that starts motion) and ``close``
(``end_all``, after the streams stopped and before the port closes).  Every other
ending asks it too, never building stop frames of its own: a stream's end and the rig
(``stop``), ``BusManager.stop_all_devices`` (``safe_commands`` for its report, then
``send_stop``), the dashboard's close (``stop``); ``motorbus.runtime.shutdown`` closes
the buses and managers (so ``end_all`` and the manager), and the guard process sends
the frames the table publishes (``bus.leases``' ``safe_frames``).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Iterable, Sequence
from typing import Protocol

from motorbus import lifecycle
from motorbus.bus import leases as _leases
from motorbus.bus.leases import Lease, LeaseTable, SafeCommandsForKey
from motorbus.bus.schedule import Priority
from motorbus.errors import BusClosedError, LocalProtocolError, MotorbusError
from motorbus.protocol import safety
from motorbus.protocol.base import Command, Family, check_flag

__all__ = [
    "SAFE_STOP_RETRIES",
    "LeaseKeeper",
    "SafeRequest",
    "SafeStopper",
    "raise_unexpected",
    "send_together",
    "together",
]

log = logging.getLogger("motorbus.bus")

#: Retries of each safe-action command, wherever a safe stop is sent (``send_together``:
#: a lease's end, a stream's safe action, BusManager, the rig; the dashboard): pause,
#: e-stop, stop project and stop all are idempotent, so sending one twice is harmless
#: and missing one is not.
SAFE_STOP_RETRIES = 2


class SafeRequest(Protocol):
    """A bus's ``request``, as ``send_together`` calls it."""

    def __call__(
        self, cmd: Command[object], *, priority: Priority, retries: int
    ) -> Awaitable[object]: ...


class SafeStopper:
    """The sending of safe actions on one bus: the commands of an action for a device
    (``motorbus.protocol.safety``) and their sending, all at once (``send_together``),
    or in steps that no cancellation cuts short (``stop_shielded``).
    ``LeaseKeeper`` is one; a served bus (``motorbus.serve.client``) has one of its own,
    whose requests go through the server.

    Args:
        name: the bus's name, for messages.
        families: the families the bus carries (a key of another family is refused).
        request: the bus's ``request``, which ``send_together`` sends safe actions with.
    """

    def __init__(self, name: str, families: frozenset[Family], request: SafeRequest) -> None:
        self.name = name
        self.families = families
        self._request = request
        self._safe_for: dict[str, SafeCommandsForKey] = {
            action: _safe_commands_for(action) for action in safety.SAFE_ACTIONS
        }

    def safe_commands(
        self, key: str, action: str = "pause", *, motor: int | None = None
    ) -> tuple[Command[object], ...]:
        """The commands of safe action ``action`` for device ``key``, in order: the same
        the table owes for a lease's end (``motorbus.protocol.safety``).  ``motor``: a
        project stepper's motor byte (default 0x03).

        Raises:
            LocalProtocolError: a bad key or action, or a family this bus does not carry.
        """
        action = safety.check_safe_action(action)
        family = safety.family_of_key(safety.check_key(key))
        if family not in self.families:
            raise LocalProtocolError(
                f"key {key!r} is a {family.value} device; bus {self.name} carries "
                f"{', '.join(sorted(f.value for f in self.families))}",
                field="key",
                value=key,
            )
        if motor is None:
            return self._safe_for[action](key)
        return safety.safe_stop_commands(key, action, motor=motor)

    async def stop(
        self, keys: Iterable[str], action: str, *, who: str, motor: int | None = None
    ) -> list[object]:
        """Bring ``keys`` to the safe state ``action`` now (``send_stop`` of their
        ``safe_commands``); an unexpected error (a bug) is raised once all went.
        Returns each command's result or exception, in order."""
        commands = [c for key in keys for c in self.safe_commands(key, action, motor=motor)]
        results = await self.send_stop(commands, who=who)
        raise_unexpected(results)
        return results

    def stop_soon(
        self, keys: Iterable[str], action: str, *, who: str, motor: int | None = None
    ) -> asyncio.Task[list[object]]:
        """``stop`` from synchronous code (an observer's callback): the commands are
        made now (a bad key raises here) and sent by a task of the running loop, which
        is returned (keep it; its failures are logged like ``send_stop``'s)."""
        commands = [c for key in keys for c in self.safe_commands(key, action, motor=motor)]
        return asyncio.get_running_loop().create_task(self.send_stop(commands, who=who))

    async def send_stop(self, commands: Sequence[Command[object]], *, who: str) -> list[object]:
        """Send safe-action commands now, all at once (``send_together``); a failure is
        logged (as ``who``'s) and stops none of the others.  Returns each command's
        result or the exception it failed with, in order.  The caller decides about
        cancellation (``send_safe`` runs to the end however often it is cancelled)."""
        results = await send_together(self._request, commands)
        for cmd, result in zip(commands, results, strict=True):
            if isinstance(result, BaseException):
                log.warning(
                    "bus %s: %s: safe action %s to %s failed: %s",
                    self.name,
                    who,
                    type(cmd).__name__,
                    cmd.device_key,
                    result,
                )
        return results

    async def stop_shielded(
        self, *steps: Sequence[Command[object]], who: str
    ) -> list[list[object]]:
        """A safe stop (a lease's end, a run abandoned, timed out or cancelled):
        ``steps`` sent in turn, each only if a command of the step before failed (a
        motor's stop, then the controller's stop all).  It runs to its end however often
        the caller is cancelled meanwhile (the cancellation is delivered after), and
        Ctrl-C waits for it.  While the port is lost, the step due is owed instead
        (``_owe_unless_open``), and its results say so.  Returns each tried step's results
        (a result or the exception, per command); an unexpected error (a bug) is raised
        once all went."""
        tried: list[list[object]] = []

        async def send() -> None:
            for commands in steps:
                refused = self._owe_unless_open(commands)
                if refused is not None:
                    tried.append([refused] * len(commands))
                    return
                results = await self.send_stop(commands, who=who)
                tried.append(results)
                if not any(isinstance(r, BaseException) for r in results):
                    return

        with lifecycle.deferred_interrupts():
            await finish_shielded(asyncio.ensure_future(send()))
        for results in tried:
            raise_unexpected(results)
        return tried

    def _owe_unless_open(self, commands: Sequence[Command[object]]) -> BusClosedError | None:
        """Why ``commands`` are not sent now, or None.  A served bus's requests go
        through its server, which keeps what its own port owes: nothing is owed here
        (``LeaseKeeper`` owes while the port is lost)."""
        return None


class LeaseKeeper(SafeStopper):
    """The leases of one bus and the sending of their safe actions.

    Args:
        name: the bus's name, for messages.
        families: the families the bus carries (a key of another family is refused).
        safe_action: the safe action of the implicit lease (``Bus(safe_action=...)``).
        request: the bus's ``request``, which ``send_together`` sends safe actions with.
        state: the bus's state now (``"open"``, ``"lost"``, ``"closed"``).
    """

    def __init__(
        self,
        name: str,
        families: frozenset[Family],
        safe_action: str,
        request: SafeRequest,
        state: Callable[[], str],
    ) -> None:
        super().__init__(name, families, request)
        self.safe_action = safe_action
        self.table = LeaseTable()
        self._state = state
        #: Safe-action commands owed while the port was lost: sent as soon as it is
        #: back (``pay_owed``, before any other traffic) or at close.
        self.owed: list[Command[object]] = []

    def lease(
        self,
        keys: Iterable[str] | str,
        owner: str,
        safe_action: str,
        *,
        bind: bool = True,
        safe_commands: Iterable[Command[object]] = (),
    ) -> Lease:
        """``Bus.lease``: check, acquire, bind to the running task."""
        action = safety.check_safe_action(safe_action)
        keys = safety.check_lease_keys(keys, self.families, self.name)
        lease = self.table.acquire(
            owner, keys, self._safe_for[action], safe_action=action, safe_commands=safe_commands
        )
        lease.releaser = self._release
        if bind:
            _leases.bind(lease)
        return lease

    def claim(self, cmd: Command[object], lease: Lease | None) -> tuple[str, ...]:
        """The lease rule of a motion command (raises ``LeaseConflictError``); returns
        the devices it moves (``safety.motion_keys``), which its write owes stops on."""
        table = self.table
        keys = safety.motion_keys(cmd)
        table.note_all(keys)
        if lease is None or lease.table is not table or not lease.active:
            lease = _leases.lease_for(table)
        if lease is None:
            lease = table.implicit(self._safe_for[self.safe_action], self.safe_action)
        table.claim(keys, lease)
        motor = getattr(cmd, "motor", None)
        if motor is not None and cmd.family is Family.PROJECT_STEPPER:
            key = cmd.device_key
            if key in lease.own_safe:
                return keys  # the owner's own safe commands: never rewritten
            table.set_safe(key, safety.safe_stop_commands(key, lease.safe_action, motor=motor))
        return keys

    async def send_stop(self, commands: Sequence[Command[object]], *, who: str) -> list[object]:
        """``SafeStopper.send_stop``, each command as it must go to its device now: an
        e-stop where a pause would lift an e-stop's latch (``LeaseTable.latched``)."""
        latched = self.table.latched
        if latched:
            commands = [safety.escalated(c, latched) for c in commands]
        return await super().send_stop(commands, who=who)

    async def release_implicit(self, keys: Iterable[str] | str | None, hold: bool) -> None:
        """``Bus.release``: end the implicit lease on ``keys`` (all if None)."""
        check_flag("hold", hold)
        table = self.table
        if keys is None:
            program = table.program
            keys = program.keys if program is not None else ()
        else:  # checked as a lease's are: a malformed key was ignored, and nothing sent
            keys = safety.check_lease_keys(keys, self.families, self.name)
        await self.send_safe(table.release_keys(keys, hold=hold))

    def hand_over(self, lease: Lease, keys: Iterable[str]) -> None:
        """``Bus.hand_over``: ``keys`` pass from ``lease`` to the implicit lease."""
        implicit = self.table.implicit(self._safe_for[self.safe_action], self.safe_action)
        self.table.hand_over(lease, keys, implicit)

    async def _release(self, lease: Lease, hold: bool, keys: frozenset[str] | None) -> None:
        hold = check_flag("hold", hold)
        await self.send_safe(self.table.release(lease, hold=hold, keys=keys))

    async def end_all(self) -> None:
        """End every lease still held, with its safe action (the bus is closing)."""
        table = self.table
        commands: list[Command[object]] = list(self.owed)
        self.owed = []
        for lease in table.leases():
            commands.extend(table.release(lease, hold=False))
        await self.send_safe(commands)

    async def pay_owed(self) -> None:
        """Send the safe actions owed since the port was lost (it is back): all
        submitted at once, so that they queue ahead of anything else."""
        owed, self.owed = self.owed, []
        if not owed:
            return
        await self.send_stop(owed, who="owed since the port was lost")

    async def send_safe(self, commands: list[Command[object]]) -> None:
        """Send safe-action commands, one failure not stopping the rest.

        Runs to its end even if the caller is cancelled meanwhile, once or more (the
        cancellation is delivered after), and Ctrl-C waits for it: a safe stop is never
        cut half way.  While the port is lost the commands are kept as owed and sent
        the moment it is back, before anything else (``pay_owed``), or at close.
        """
        if commands and self._owe_unless_open(commands) is None:
            await self.stop_shielded(commands, who="a lease ended")

    def _owe_unless_open(self, commands: Sequence[Command[object]]) -> BusClosedError | None:
        """None while the bus is open.  Else why ``commands`` are not sent now, logged:
        owed while the port is lost (sent the moment it is back, ``pay_owed``, or at
        close), dropped once the bus is closed."""
        state = self._state()
        if state == "open":
            return None
        keys = ", ".join(dict.fromkeys(c.device_key for c in commands))
        if state == "closed":
            why = f"bus {self.name} is closed: could not send the safe action to {keys}"
        else:
            why = (
                f"bus {self.name} is {state}: the safe action to {keys} is owed; it goes "
                "out the moment the port is back"
            )
            self.owed.extend(commands)
        log.warning("%s", why)
        return BusClosedError(why)


async def send_together(request: SafeRequest, commands: Sequence[Command[object]]) -> list[object]:
    """Send every command of a safe stop with ``request`` (a bus's), at emergency
    priority with ``SAFE_STOP_RETRIES``, all at once; wait for them all.  Returns each
    one's result, or the exception it failed with, in the order of ``commands``.

    Submitted in one go, they queue in their order, and commands to one device keep it
    (``motorbus.bus.schedule.keeps_order``).  A device that does not answer holds up no
    other: its retries wait out its late guard while the other devices' commands go.
    (Sent one after another, a silent actuator held every stop behind it for its
    attempts and guards: 25-50 ms each.)  The safe stops of leases, streams, the
    manager's stop plan and the rig go through here.
    """
    sent = (
        request(cmd, priority=Priority.EMERGENCY, retries=SAFE_STOP_RETRIES) for cmd in commands
    )
    return list(await asyncio.gather(*sent, return_exceptions=True))


def raise_unexpected(results: Iterable[object]) -> None:
    """Raise the first exception of ``send_together``'s results that is not a bus's
    (``MotorbusError``) or the port's (``OSError``): a bug, once every command went."""
    for result in results:
        if isinstance(result, BaseException) and not isinstance(result, MotorbusError | OSError):
            raise result


async def together(
    awaitables: Sequence[Awaitable[object]], failed: Callable[[int, Exception], None]
) -> BaseException | None:
    """Await every one of ``awaitables`` at once, so that a silent device behind one
    holds up no other's stop.  Each that fails with an ``Exception`` goes to ``failed``
    (with its index) and stops nothing; the first other ``BaseException`` is returned,
    for the caller to raise once its own closing is done."""
    outcomes = await asyncio.gather(*awaitables, return_exceptions=True)
    interrupted: BaseException | None = None
    for i, outcome in enumerate(outcomes):
        if isinstance(outcome, Exception):
            failed(i, outcome)
        elif isinstance(outcome, BaseException) and interrupted is None:
            interrupted = outcome
    return interrupted


async def finish_shielded(fut: asyncio.Future[None]) -> None:
    """Await ``fut`` to its end however often the caller is cancelled meanwhile, then
    deliver the cancellation (``asyncio.shield`` alone gives it back at once, and a
    second cancellation would leave the safe stop to a loop that may be closing)."""
    cancelled = False
    while not fut.done():
        try:
            await asyncio.shield(fut)
        except asyncio.CancelledError:
            # Delivered after, also when ``fut`` ended in the same loop step.
            cancelled = True
    if cancelled:
        if not fut.cancelled() and fut.exception() is not None:
            log.warning("a safe stop failed while its caller was cancelled: %s", fut.exception())
        raise asyncio.CancelledError
    fut.result()


def _safe_commands_for(action: str) -> SafeCommandsForKey:
    """Key -> the commands of ``action`` for it (``safety.safe_stop_commands``)."""

    def safe_for(key: str) -> tuple[Command[object], ...]:
        return safety.safe_stop_commands(key, action)

    return safe_for
