"""Leases: one owner per moving device, and a safe end for every motion.

Pure (no asyncio, no clock): the table below is what ``Bus`` consults in one place, the
submit of a command that ``starts_motion``, and what it applies in one place, its close.

* Whoever moves a device holds a **lease** on it: an explicit one (``bus.lease(keys,
  owner=...)``: a stream, a rig, a CLI command) or, for motion sent outside any lease
  (a plain ``move_to``), the bus's **implicit** lease, owner ``"program"``.
* A motion command for a device that another explicit lease holds is refused with
  ``LeaseConflictError`` before anything is sent.  An explicit lease takes devices over
  from the implicit one (the same program moved them before, e.g. a ``move_to`` to the
  start of a stream); never from another explicit lease.
* Every leased device has a **safe action** (``motorbus.protocol.safety``: an LA pause or
  e-stop, a stepper stop) and a record of what of it is still owed: all of it from an
  explicit lease's start; after every motion frame written, what ends that motion (an
  LA's pause, the stop project after a project start, a quad motor's stop after its
  run).  A command that covers it (``safety.covers``), written and answered if it
  expects a reply, pays it: the owner's own stop, a stream's safe action, a
  ``BusManager``'s stop, or the device's report that the motion ended (``EE DD``, a quad
  run's done reply).
* An owner may give some devices **safe commands of its own** (``bus.lease(...,
  safe_commands=[...])``): they replace the safe action's for the devices they address,
  owed from the lease's start like any safe action, and the bus never rewrites them.  A
  project upload's lease owes the clear of the project it writes (0x1E): a half-written
  project must not look valid after the program is killed.
* A lease ends by ``release(hold=False)``: the safe actions still owed are returned for
  the bus to send; with ``hold=True`` nothing is (the owner ends on purpose and the
  devices keep their last command).  The bus ends every lease still held when it closes,
  after its streams stopped and before the port closes.

Device keys are ``Command.device_key`` strings: ``"la:3"``, ``"project_stepper"``,
``"quad_stepper"``.  ``"la:255"`` (an LA command to every actuator) stands for every LA
that answered on the bus or was moved by its ID so far (itself if there is none yet: its
safe action is then a pause to ID 255).
"""

from __future__ import annotations

import contextvars
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, TypeAlias

from motorbus.errors import LeaseConflictError, LocalProtocolError
from motorbus.protocol import safety
from motorbus.protocol.base import Command
from motorbus.protocol.families import FAMILIES

__all__ = [
    "PROGRAM",
    "DeviceKey",
    "Lease",
    "LeaseConflictError",
    "LeaseInfo",
    "LeaseTable",
    "SafeCommandsForKey",
    "bind",
    "current_leases",
    "lease_for",
    "own_safe_commands",
]

#: A device on a bus, as ``Command.device_key`` names it.
DeviceKey: TypeAlias = str
#: The owner of the implicit lease: motion sent outside any explicit lease.
PROGRAM = "program"
#: Given a key, the commands of its safe action (``safety.safe_stop_commands``).
SafeCommandsForKey: TypeAlias = Callable[[DeviceKey], "tuple[Command[object], ...]"]
#: Longest owner name (it appears in errors, logs and the guard's records).
OWNER_MAX = 200

#: Keys that stand for every device of a family that answered or was moved ("la:255").
_WILDCARDS = {
    f"{info.key}:{info.broadcast_id}": f"{info.key}:"
    for info in FAMILIES.values()
    if info.broadcast_id is not None
}

_WILDCARD_KEYS = frozenset(_WILDCARDS)

#: The explicit leases a task holds (acquired in it, or in the task that started it).
_current: contextvars.ContextVar[tuple[Lease, ...]] = contextvars.ContextVar(
    "motorbus_leases", default=()
)


def current_leases() -> tuple[Lease, ...]:
    """The explicit leases the running task holds (most recent last)."""
    return _current.get()


@dataclass(frozen=True, slots=True)
class LeaseInfo:
    """One leased device, as ``bus.leases`` and lease listeners see it.

    Attributes:
        key: the device (``"la:3"``).
        owner: who holds it (``"program"`` for the implicit lease).
        safe_frames: the encoded frames of its safe action, in order (empty for hold);
            what a guard process sends if the program dies holding the lease.
    """

    key: DeviceKey
    owner: str
    safe_frames: tuple[bytes, ...]


class Lease:
    """A claim on devices: while it is held, nobody else moves them.

    Made by ``bus.lease(keys, owner=..., safe_action=...)``; motion submitted from the
    task that acquired it (and from tasks that task starts afterwards) belongs to it.
    Use it as ``async with bus.lease(...) as lease:``: leaving the block, however it is
    left (normally, by an exception, by cancellation), releases it with its safe action.

    Attributes:
        owner: the name given at acquisition.
        safe_action: ``"pause"``, ``"estop"`` or ``"hold"``.
        implicit: True for the bus's own lease (owner ``"program"``).
        own_safe: the devices whose safe commands the owner gave (``safe_commands``);
            the bus never rewrites them (e.g. with a motor byte learnt from motion).
    """

    def __init__(
        self,
        table: LeaseTable,
        owner: str,
        safe_for: SafeCommandsForKey,
        *,
        safe_action: str = "pause",
        implicit: bool = False,
    ) -> None:
        self.table = table
        self.owner = owner
        self.safe_action = safe_action
        self.implicit = implicit
        self.safe_for = safe_for
        self.own_safe: frozenset[DeviceKey] = frozenset()
        self.active = True
        #: Set by the bus: sends what ``LeaseTable.release`` returns.
        self.releaser: Callable[[Lease, bool, frozenset[DeviceKey] | None], Any] | None = None
        #: Called with ``(keys, hold)`` as ``release`` begins, before anything is sent
        #: (``keys`` None: all of them): a stream running under this lease stops there,
        #: so nothing of it follows the lease's safe action.
        self.enders: list[Callable[[frozenset[DeviceKey] | None, bool], Any]] = []
        #: Stops written to its devices while it held them, by anyone, by device: a
        #: stream under this lease ends on one (``motorbus.streams``).
        self.stopped: dict[DeviceKey, Command[object]] = {}

    def __repr__(self) -> str:
        state = "held" if self.active else "released"
        return f"Lease(owner={self.owner!r}, keys={sorted(self.keys)}, {state})"

    @property
    def keys(self) -> frozenset[DeviceKey]:
        """The devices this lease holds now (it grows when it moves a free device)."""
        return self.table.keys_of(self)

    def add(self, keys: Iterable[DeviceKey] | DeviceKey) -> None:
        """Hold more devices (a streamer whose next stream names new actuators).

        Raises:
            LeaseConflictError: another explicit lease holds one of them (nothing
                changes).
        """
        self.table.add(self, keys)

    async def release(self, *, hold: bool = False, keys: Iterable[DeviceKey] | None = None) -> None:
        """End the lease.  Without ``hold``, every device it holds gets its safe action
        (the ones not already brought to it since their last motion); with
        ``hold=True`` nothing is sent and each device keeps its last command: the owner
        ends on purpose.  Idempotent.

        With ``keys``, only those devices are let go (e.g. the actuators of one of a
        streamer's streams); the lease stays held for the others.
        """
        if not self.active:
            return
        # Checked as a lease's keys are (a malformed one was let go of silently: nothing).
        wanted = None if keys is None else frozenset(self.table._wanted(keys))
        failed: Exception | None = None
        try:
            for ender in list(self.enders):
                try:
                    await ender(wanted, hold)
                except Exception as err:  # the lease still ends: raised after
                    failed = failed or err
        finally:  # cancelled or not, the lease ends with its safe action
            if self.releaser is not None:
                await self.releaser(self, hold, wanted)
            else:
                self.table.release(self, hold=hold, keys=wanted)
        if failed is not None:
            raise failed

    def forget_stops(self, keys: Iterable[DeviceKey]) -> None:
        """Forget the stops noted on ``keys`` (``stopped``): a new stream drives them."""
        for key in keys:
            self.stopped.pop(key, None)

    async def __aenter__(self) -> Lease:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.release(hold=False)


@dataclass(slots=True)
class _Entry:
    lease: Lease
    safe: tuple[Command[object], ...]
    #: Safe commands not written (and answered) since the device last moved.
    owed: tuple[Command[object], ...]


class LeaseTable:
    """Who holds which device, and which safe actions are still owed.

    Pure bookkeeping; the bus sends what ``release`` returns.  Every change calls the
    listeners with the new ``snapshot()``.
    """

    def __init__(self) -> None:
        self._entries: dict[DeviceKey, _Entry] = {}
        self._seen: set[DeviceKey] = set()
        self._program: Lease | None = None
        self._listeners: list[Callable[[tuple[LeaseInfo, ...]], None]] = []
        #: Counts every change of who holds what (and of the keys seen, which a
        #: wildcard stands for): a claim checked at one version holds at the same one.
        self.version = 0
        #: Counts every change of what a device owes; with ``version``, it dates the
        #: memos of the hot paths below (a stream's tick claims and moves the same keys
        #: every tick): a memo of the same keys at the same dates still holds.
        self._owed_epoch = 0
        self._claimed: tuple[Any, ...] = ()  # (keys, lease, version) of a claim that held
        #: LAs e-stopped (an e-stop written, no "work" since: ``safety.latch_change``):
        #: a safe action to one is an e-stop, not a pause that lifts it (``LeaseKeeper``).
        self.latched: set[DeviceKey] = set()
        self._settled: tuple[Any, ...] = ()  # (keys, stops, version, epoch) of a no-op moved

    # -- reading ---------------------------------------------------------------------

    def owner_of(self, key: DeviceKey) -> str | None:
        """Who holds ``key`` (``"program"`` for the implicit lease), or None."""
        entry = self._entries.get(key)
        return None if entry is None else entry.lease.owner

    def keys_of(self, lease: Lease) -> frozenset[DeviceKey]:
        """The keys ``lease`` holds."""
        return frozenset(k for k, e in self._entries.items() if e.lease is lease)

    def leases(self) -> list[Lease]:
        """Every lease that holds a device, in acquisition order of their first key."""
        return list(dict.fromkeys(e.lease for e in self._entries.values()))

    def owed(self, key: DeviceKey) -> tuple[Command[object], ...]:
        """The safe commands ``key`` still needs (empty: it is at rest, or not leased)."""
        entry = self._entries.get(key)
        return () if entry is None else entry.owed

    def snapshot(self) -> tuple[LeaseInfo, ...]:
        """Every leased device with its owner and safe frames, sorted by key."""
        return tuple(
            LeaseInfo(k, e.lease.owner, tuple(c.encode() for c in e.safe))
            for k, e in sorted(self._entries.items())
        )

    @property
    def program(self) -> Lease | None:
        """The implicit lease, if motion was sent outside any explicit lease."""
        return self._program

    # -- listeners -------------------------------------------------------------------

    def add_listener(self, fn: Callable[[tuple[LeaseInfo, ...]], None]) -> None:
        """Call ``fn(snapshot)`` after every change."""
        self._listeners.append(fn)

    def remove_listener(self, fn: Callable[[tuple[LeaseInfo, ...]], None]) -> None:
        """Forget ``fn``; unknown ones are ignored."""
        if fn in self._listeners:
            self._listeners.remove(fn)

    def _changed(self) -> None:
        self.version += 1
        self._owed_epoch += 1  # entries came or went, or a safe action changed
        if self._listeners:
            snap = self.snapshot()
            for fn in list(self._listeners):
                fn(snap)

    # -- keys ------------------------------------------------------------------------

    def note(self, key: DeviceKey) -> None:
        """Remember that ``key`` answered on the bus, or was moved by name (what
        ``"la:255"`` stands for: not every ID a scan asked)."""
        seen = self._seen
        if key not in seen:
            seen.add(key)
            self.version += 1

    def note_all(self, keys: Iterable[DeviceKey]) -> None:
        """``note`` each of ``keys``."""
        seen = self._seen
        keys = tuple(keys)
        if not seen.issuperset(keys):  # a stream's every tick: one call, all known
            seen.update(keys)
            self.version += 1

    def expand(self, keys: Iterable[DeviceKey]) -> tuple[DeviceKey, ...]:
        """``keys`` with each wildcard (``"la:255"``) replaced by the family's devices
        that answered, were moved by ID or are leased (the wildcard itself if there are none)."""
        out: list[DeviceKey] = []
        for key in keys:
            prefix = _WILDCARDS.get(key)
            if prefix is None:
                out.append(key)
                continue
            known = sorted(
                (k for k in self._seen | set(self._entries) if k.startswith(prefix)),
                key=lambda k: (len(k), k),
            )
            out.extend([k for k in known if k not in _WILDCARDS] or [key])
        return tuple(dict.fromkeys(out))

    # -- acquiring -------------------------------------------------------------------

    def acquire(
        self,
        owner: str,
        keys: Iterable[DeviceKey],
        safe_commands_for_key: SafeCommandsForKey,
        *,
        safe_action: str = "pause",
        safe_commands: Iterable[Command[object]] = (),
    ) -> Lease:
        """A new explicit lease of ``owner`` on ``keys``.

        Args:
            safe_commands: commands of the owner's own safe end, in order; for each
                device they address (``device_key``) they replace what
                ``safe_commands_for_key`` gives (see ``own_safe_commands``).

        Raises:
            LeaseConflictError: another explicit lease holds one of the keys (nothing
                changes).  Keys of the implicit lease are taken over.
            LocalProtocolError: a bad owner or key, or no key at all; a safe command
                that is no command, starts motion or addresses a device not among
                ``keys``.
        """
        owner = _check_owner(owner)
        wanted = self._wanted(keys)
        if not wanted:
            raise LocalProtocolError("a lease needs at least one device key", field="keys")
        own = own_safe_commands(safe_commands, wanted)
        self._check_free(wanted, owner, None)
        safe_for = safe_commands_for_key
        if own:

            def safe_for(key: DeviceKey) -> tuple[Command[object], ...]:
                return own[key] if key in own else safe_commands_for_key(key)

        lease = Lease(self, owner, safe_for, safe_action=safe_action)
        lease.own_safe = frozenset(own)
        self._hold(lease, wanted)
        return lease

    def add(self, lease: Lease, keys: Iterable[DeviceKey] | DeviceKey) -> None:
        """``lease`` holds ``keys`` too (all of their safe action owed from now).

        Raises:
            LeaseConflictError: another explicit lease holds one of them.
            LocalProtocolError: a bad key, or ``lease`` was released.
        """
        if not lease.active or lease.implicit:
            raise LocalProtocolError(
                f"{lease!r} can take no more devices: it is released or implicit", field="lease"
            )
        wanted = self._wanted(keys)
        self._check_free(wanted, lease.owner, lease)
        self._hold(lease, [k for k in wanted if not self._is(k, lease)])

    def _wanted(self, keys: Iterable[DeviceKey] | DeviceKey) -> tuple[DeviceKey, ...]:
        return self.expand(safety.check_key(k) for k in safety.as_keys(keys))

    def _is(self, key: DeviceKey, lease: Lease) -> bool:
        entry = self._entries.get(key)
        return entry is not None and entry.lease is lease

    def _check_free(self, keys: Iterable[DeviceKey], owner: str, lease: Lease | None) -> None:
        for key in keys:
            entry = self._entries.get(key)
            if entry is not None and not entry.lease.implicit and entry.lease is not lease:
                raise LeaseConflictError(key, entry.lease.owner, owner)

    def _hold(self, lease: Lease, keys: Iterable[DeviceKey]) -> None:
        changed = False
        for key in keys:
            safe = lease.safe_for(key)
            self._entries[key] = _Entry(lease, safe, safe)  # all of it owed from the start
            changed = True
        if changed:
            self._changed()

    def implicit(self, safe_commands_for_key: SafeCommandsForKey, safe_action: str) -> Lease:
        """The implicit lease (made on first use)."""
        if self._program is None or not self._program.active:
            self._program = Lease(
                self, PROGRAM, safe_commands_for_key, safe_action=safe_action, implicit=True
            )
        return self._program

    def claim(self, keys: Iterable[DeviceKey], lease: Lease) -> bool:
        """Motion of ``lease`` (explicit, or the implicit one) for ``keys``: check and hold.

        Free keys join ``lease``; keys of the implicit lease move to an explicit one.
        Returns True if the table changed.

        Raises:
            LeaseConflictError: another explicit lease holds one of the keys (nothing
                changes).
        """
        claimed = self._claimed
        if (
            claimed
            and claimed[1] is lease
            and claimed[2] == self.version
            and claimed[0] == keys
            and lease.active
        ):
            return False  # the hottest path: the same keys as the last tick, nothing changed
        entries = self._entries
        for key in keys:  # the hot path (every stream tick): all held already
            entry = entries.get(key)
            if entry is None or entry.lease is not lease or key in _WILDCARDS:
                break
        else:
            if isinstance(keys, tuple):
                self._claimed = (keys, lease, self.version)
            return False
        changed = False
        keys = self.expand(keys)
        for key in keys:
            entry = entries.get(key)
            if entry is not None and entry.lease is not lease and not entry.lease.implicit:
                raise LeaseConflictError(key, entry.lease.owner, lease.owner)
        for key in keys:
            entry = entries.get(key)
            if entry is None or entry.lease is not lease:
                # Owed: what the implicit lease owed; the motion adds its own (``moved``).
                owed = () if entry is None else entry.owed
                entries[key] = _Entry(lease, lease.safe_for(key), owed)
                changed = True
        if changed:
            self._changed()
        return changed

    def set_safe(self, key: DeviceKey, commands: tuple[Command[object], ...]) -> None:
        """Replace ``key``'s safe commands (a project stepper's motor byte, learnt from
        its motion)."""
        entry = self._entries.get(key)
        if entry is None or entry.safe == commands:
            return
        entry.safe = commands
        self._changed()

    # -- what the bus wrote ------------------------------------------------------------

    def moved(self, cmd: Command[object], keys: tuple[DeviceKey, ...] | None = None) -> None:
        """The motion frame ``cmd`` was written: what ends its motion is owed, on each
        device it moves, besides what was owed already (``safety.motion_stops``; the
        device's whole safe action where the motion names no smaller stop).  ``keys``:
        ``safety.motion_keys(cmd)``, if the caller has them already."""
        if keys is None:
            keys = safety.motion_keys(cmd)
        stops = safety.motion_stops(cmd)
        settled = self._settled
        if (
            settled
            and settled[1] is stops
            and settled[2] == self.version
            and settled[3] == self._owed_epoch
            and settled[0] == keys
        ):
            return  # the same motion as the last tick's, and nothing owed changed since
        memo = (keys, stops, self.version, self._owed_epoch)
        if not _WILDCARD_KEYS.isdisjoint(keys):
            keys = self.expand(keys)
        entries = self._entries
        for key in keys:
            entry = entries.get(key)
            if entry is None:
                continue
            # A "hold" lease's devices have no safe action, so they owe nothing.
            owes = entry.safe if stops is None or not entry.safe else stops
            owed = entry.owed
            if owed is owes or not owes:
                continue  # the hot path: a streamed actuator owes its pause already
            if not owed:
                entry.owed = owes
                self._owed_epoch += 1
            elif owed != owes:
                entry.owed = tuple(dict.fromkeys((*owed, *owes)))
                self._owed_epoch += 1
        if memo[3] == self._owed_epoch:
            self._settled = memo  # nothing changed: the same motion again is a no-op

    def sent(
        self, cmd: Command[object], key: DeviceKey | None = None, *, written: bool = True
    ) -> None:
        """``cmd`` was written (and answered, if it expects a reply): what it covers of
        the safe actions owed is paid, and a stop is noted on the lease of each device
        it stops (``Lease.stopped``).  ``key``: its ``device_key``, if known.
        ``written=False``: not a frame but what a device's own end counts as (a
        project's ``EE DD``, a quad run's done): it pays, and is no stop of anyone's."""
        if key is None:
            key = cmd.device_key
        if key in _WILDCARDS:
            held = self._held(key)
        else:  # (``_held`` inline: every answered request comes here)
            entry = self._entries.get(key)
            held = [] if entry is None else [(key, entry)]
        if written:
            self._note(cmd, key, held)
        for _, entry in held:
            owed = entry.owed
            if owed:
                left = safety.pending_after(cmd, owed)
                if len(left) != len(owed):  # something was paid (a status read pays nothing)
                    entry.owed = left
                    self._owed_epoch += 1

    def unanswered(self, cmd: Command[object], key: DeviceKey) -> None:
        """``cmd`` was written, its answer never came: noted as ``sent`` notes it (a stop
        may have taken effect), but it pays nothing owed; an unanswered "work" clears
        no latch."""
        if safety.latch_change(cmd) is not False:
            self._note(cmd, key, self._held(key))

    def _held(self, key: DeviceKey) -> list[tuple[DeviceKey, _Entry]]:
        """The entries ``key`` names (each of its family's for a wildcard), by key."""
        if key in _WILDCARDS:
            return [(k, e) for k, e in self._entries.items() if k.startswith(_WILDCARDS[key])]
        return [(key, self._entries[key])] if key in self._entries else []

    def _note(
        self, cmd: Command[object], key: DeviceKey, held: list[tuple[DeviceKey, _Entry]]
    ) -> None:
        """``cmd`` written to ``key`` (``held``: its entries): a latch set or cleared
        (``latched``), a stop noted on the lease of each device (``Lease.stopped``)."""
        latch = safety.latch_change(cmd)
        if latch is not None:
            keys = self.expand((key,)) if key in _WILDCARDS else (key,)
            if latch:
                self.latched.update(keys)
            else:
                self.latched.difference_update(keys)
        if held and safety.is_stop(cmd):
            for k, entry in held:
                entry.lease.stopped[k] = cmd

    # -- releasing -------------------------------------------------------------------

    def release(
        self, lease: Lease, *, hold: bool, keys: Iterable[DeviceKey] | None = None
    ) -> list[Command[object]]:
        """End ``lease`` (only its ``keys`` if given: it stays held for the others): the
        devices are free.  Returns the safe commands still owed, device by device
        (nothing with ``hold``), for the bus to send."""
        held = self.keys_of(lease)
        ending = held if keys is None else held & frozenset(keys)
        commands: list[Command[object]] = []
        for key in sorted(ending, key=lambda k: (len(k), k)):
            entry = self._entries.pop(key)
            if not hold:
                commands.extend(entry.owed)
        if keys is None:
            lease.active = False
            if lease is self._program:
                self._program = None
        self._changed()
        return commands

    def hand_over(self, lease: Lease, keys: Iterable[DeviceKey], to: Lease) -> None:
        """``lease`` lets go of ``keys`` (those it holds) without a word on the wire; they
        pass to ``to`` (the implicit lease), owing ``to``'s whole safe action: the devices
        were moved, and hold until ``to`` ends (the bus closing stops them)."""
        held = self.keys_of(lease) & frozenset(keys)
        for key in held:
            safe = to.safe_for(key)
            self._entries[key] = _Entry(to, safe, safe)
        if held:
            self._changed()

    def release_keys(self, keys: Iterable[DeviceKey], *, hold: bool) -> list[Command[object]]:
        """End the implicit lease on ``keys`` (the others it holds stay).  Returns the
        safe commands owed (nothing with ``hold``).

        Raises:
            LeaseConflictError: an explicit lease holds one of the keys; release that
                lease instead (nothing changes).
        """
        wanted = self.expand(keys)
        for key in wanted:
            entry = self._entries.get(key)
            if entry is not None and not entry.lease.implicit:
                raise LeaseConflictError(key, entry.lease.owner, PROGRAM)
        commands: list[Command[object]] = []
        changed = False
        for key in wanted:
            entry = self._entries.pop(key, None)
            if entry is None:
                continue
            changed = True
            if not hold:
                commands.extend(entry.owed)
        if changed:
            self._changed()
        return commands


def own_safe_commands(
    commands: Iterable[Command[object]], keys: Iterable[DeviceKey]
) -> dict[DeviceKey, tuple[Command[object], ...]]:
    """An owner's own safe commands, grouped by the device each addresses (in order).

    A device of ``keys`` that none addresses keeps the lease's safe action.

    Raises:
        LocalProtocolError: a safe command that is no ``Command``, that starts motion
            (a safe end never moves anything), or whose device is not one of ``keys``
            (``"la:255"`` is not allowed: name each actuator).
    """
    held = frozenset(keys)
    own: dict[DeviceKey, tuple[Command[object], ...]] = {}
    if isinstance(commands, Command) or not isinstance(commands, Iterable):
        raise LocalProtocolError(
            f"safe_commands must be a list of motorbus Commands, got {commands!r}",
            field="safe_commands",
        )
    for cmd in commands:
        if not isinstance(cmd, Command):
            raise LocalProtocolError(
                f"safe_commands: {cmd!r} is not a motorbus Command", field="safe_commands"
            )
        if cmd.starts_motion:
            raise LocalProtocolError(
                f"safe_commands: {type(cmd).__name__} starts motion: a safe end must not",
                field="safe_commands",
            )
        key = cmd.device_key
        if key in _WILDCARDS:
            raise LocalProtocolError(
                f"safe_commands: {type(cmd).__name__} addresses {key} (every device of "
                "its family): give each device's own commands",
                field="safe_commands",
            )
        if key not in held:
            raise LocalProtocolError(
                f"safe_commands: {type(cmd).__name__} addresses {key}, which the lease "
                f"does not hold ({', '.join(sorted(held))})",
                field="safe_commands",
            )
        own[key] = (*own.get(key, ()), cmd)
    return own


def bind(lease: Lease) -> None:
    """Make ``lease`` the running task's (and its future child tasks')."""
    _current.set((*(held for held in _current.get() if held.active), lease))


def lease_for(table: LeaseTable) -> Lease | None:
    """The most recent active explicit lease of ``table`` the running task holds."""
    for lease in reversed(_current.get()):
        if lease.table is table and lease.active:
            return lease
    return None


def _check_owner(owner: object) -> str:
    if not isinstance(owner, str) or not owner.strip() or len(owner) > OWNER_MAX:
        raise LocalProtocolError(
            f"owner={owner!r} is not allowed: a non-empty name of at most {OWNER_MAX} characters",
            field="owner",
            value=owner,
        )
    if owner == PROGRAM:
        raise LocalProtocolError(
            f"owner={owner!r} is reserved for motion sent outside any lease: pick another",
            field="owner",
            value=owner,
        )
    return owner
