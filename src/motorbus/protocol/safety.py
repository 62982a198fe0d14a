"""Safe actions, as values: what brings a device to rest, and what counts as having done so.

Sans-I/O.  One place for the stop commands of every family, so that the devices, the
bus's leases (``motorbus.bus.leases``), the ``BusManager`` and a guard process all send
the same frames:

* an LA actuator (``"la:ID"``): CMD_MC pause (power stage off; the next target resumes)
  or e-stop (power stage off until "work"), LA manual 3.5.4;
* the project stepper (``"project_stepper"``): stop project (0x5E), then stop manual
  motion of its motor (0x0D);
* the quad stepper (``"quad_stepper"``): stop all.

``"hold"`` is the choice of sending nothing (each device keeps its last command).

    >>> from motorbus.protocol.safety import safe_stop_commands
    >>> safe_stop_commands("la:3", "estop")
    (Control(id=3, action=<ControlAction.ESTOP: 35>),)
"""

from __future__ import annotations

from collections.abc import Container, Iterable

from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import Command, Family
from motorbus.protocol.families import FAMILIES

# The stepper families are imported inside the functions, where a stepper command is at
# hand (a command of a family means its module is loaded, so the import is a dict
# look-up): a program or a ``motorbus la`` command that only speaks to LA actuators does
# not pay the 60 ms it takes to import them (tests/cli/test_cli_startup.py).

__all__ = [
    "AT_REST_AFTER_PROJECT_END",
    "SAFE_ACTIONS",
    "as_keys",
    "at_rest_after_done",
    "check_key",
    "check_lease_keys",
    "check_safe_action",
    "covers",
    "escalated",
    "family_of_key",
    "is_stop",
    "latch_change",
    "motion_keys",
    "motion_stops",
    "pending_after",
    "safe_stop_commands",
    "watch_allowed",
]

#: The safe actions a lease, a stream or a bus file may name.
SAFE_ACTIONS = ("pause", "estop", "hold")
#: LA control sub-commands that leave the power stage off, and which of them each covers:
#: an e-stop is at least as safe as a pause (a pause after it would undo its latch).
_LA_STOPS = {
    la.ControlAction.PAUSE: frozenset({la.ControlAction.PAUSE}),
    la.ControlAction.ESTOP: frozenset({la.ControlAction.PAUSE, la.ControlAction.ESTOP}),
}
_LA_PREFIX = f"{Family.LA.value}:"
#: "la:0".."la:255", built once: a stream's broadcast names up to 31 of them per tick.
_LA_KEYS = tuple(f"{_LA_PREFIX}{ident}" for ident in range(la.BROADCAST_ID + 1))


def check_safe_action(action: object, field: str = "safe_action") -> str:
    """``action`` as one of ``SAFE_ACTIONS`` (an enum member gives its ``value``).

    Raises:
        LocalProtocolError: anything else, naming ``field``, the value and the choices.
    """
    name = getattr(action, "value", action)
    if not isinstance(name, str) or name not in SAFE_ACTIONS:
        raise LocalProtocolError(
            f"{field}={action!r} is not allowed: choose {', '.join(SAFE_ACTIONS)}",
            field=field,
            value=action,
        )
    return name


def family_of_key(key: str) -> Family:
    """The family a device key (``"la:3"``, ``"quad_stepper"``) belongs to."""
    if key.startswith(_LA_PREFIX):
        return Family.LA
    for family in FAMILIES:
        if key == family.value:
            return family
    raise LocalProtocolError(
        f"device key {key!r} is unknown: use 'la:ID' (ID 1..{la.ID_MAX}), "
        "'project_stepper' or 'quad_stepper'",
        field="key",
        value=key,
    )


def check_key(key: object) -> str:
    """``key`` if it names a device (``la:1``..``la:254``, ``la:255`` for every LA,
    ``project_stepper``, ``quad_stepper``); ``LocalProtocolError`` otherwise."""
    if not isinstance(key, str):
        raise LocalProtocolError(f"a device key is a string, got {key!r}", field="key", value=key)
    if family_of_key(key) is Family.LA:
        text = key[len(_LA_PREFIX) :]
        if not text.isdigit() or not la.ID_MIN <= int(text) <= la.BROADCAST_ID:
            raise LocalProtocolError(
                f"device key {key!r}: the LA ID must be {la.ID_MIN}..{la.ID_MAX} "
                f"({la.BROADCAST_ID}: every actuator)",
                field="key",
                value=key,
            )
    return key


def as_keys(keys: Iterable[str] | str) -> tuple[str, ...]:
    """``keys`` (one device key, or several) as a tuple; ``LocalProtocolError`` for
    anything else (the keys themselves are checked by ``check_key``)."""
    if isinstance(keys, str):
        return (keys,)
    try:
        return tuple(keys)
    except TypeError:
        raise LocalProtocolError(
            f'keys must be a device key ("la:3", "project_stepper", "quad_stepper") or '
            f"several, got {keys!r}",
            field="keys",
            value=keys,
        ) from None


def check_lease_keys(
    keys: Iterable[str] | str, families: Iterable[Family], bus: str
) -> tuple[str, ...]:
    """The keys of a lease on bus ``bus``, each a device key of a family the bus
    carries (``LocalProtocolError`` naming the key otherwise: nothing is taken)."""
    wanted = as_keys(keys)
    carried = frozenset(families)
    for key in wanted:
        family = family_of_key(check_key(key))
        if family not in carried:
            raise LocalProtocolError(
                f"key {key!r} is a {family.value} device; bus {bus} carries "
                f"{', '.join(sorted(f.value for f in carried))}",
                field="keys",
                value=key,
            )
    return wanted


def safe_stop_commands(
    key: str, action: object = "pause", *, motor: int | None = None
) -> tuple[Command[object], ...]:
    """The commands that bring device ``key`` to rest, in the order to send them.

    Args:
        key: a device key (``Command.device_key``): ``"la:3"``, ``"project_stepper"``,
            ``"quad_stepper"``.
        action: ``"pause"``, ``"estop"`` or ``"hold"`` (nothing).  The steppers know one
            way to stop: pause and e-stop both send it.
        motor: the project stepper's motor byte (default 0x03, A0-02).
    """
    name = check_safe_action(action, "action")
    family = family_of_key(check_key(key))
    if name == "hold":
        return ()
    if family is Family.LA:
        sub = la.ControlAction.ESTOP if name == "estop" else la.ControlAction.PAUSE
        return (la.Control(int(key[len(_LA_PREFIX) :]), sub),)
    if family is Family.PROJECT_STEPPER:
        from motorbus.protocol import project_stepper as ps

        return (ps.StopProject(), ps.ManualStop(motor=ps.DEFAULT_MOTOR if motor is None else motor))
    from motorbus.protocol import quad_stepper as q

    return (q.StopAll(),)


def motion_stops(cmd: Command[object]) -> tuple[Command[object], ...] | None:
    """What ends the motion ``cmd`` starts, where that is less than the device's whole
    safe action: the stop project after a project start, the motor's manual stop after a
    jog, a single run or homing, a quad motor's stop after its run or homing.  ``None``
    means the device's safe action itself (an LA's pause or e-stop, a quad's stop all)."""
    if cmd.family is Family.LA:
        return None  # the stream's path: no isinstance chain
    if cmd.family is Family.PROJECT_STEPPER:
        from motorbus.protocol import project_stepper as ps

        if isinstance(cmd, ps.StartProject):
            return (ps.StopProject(),)
        if isinstance(cmd, ps.ProjectStepperCommand):
            return (ps.ManualStop(motor=getattr(cmd, "motor", ps.DEFAULT_MOTOR)),)
        return None
    from motorbus.protocol import quad_stepper as q

    if isinstance(cmd, (q.Run, q.Home)):
        return (q.Stop(cmd.motor),)
    return None


def at_rest_after_done(cmd: Command[object]) -> Command[object] | None:
    """The stop a motion's own "done" reply is as good as (a quad run's done: that
    motor's stop), or None."""
    if cmd.family is not Family.QUAD_STEPPER:
        return None
    from motorbus.protocol import quad_stepper as q

    return q.Stop(cmd.motor) if isinstance(cmd, q.Run) else None


#: A project's end (``EE DD``) is as good as a stop project (made on first use, by the
#: module ``__getattr__`` below: only a project stepper's bus reads it).
AT_REST_AFTER_PROJECT_END: Command[object]


def __getattr__(name: str) -> object:
    if name == "AT_REST_AFTER_PROJECT_END":
        from motorbus.protocol import project_stepper as ps

        value = ps.StopProject()
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def watch_allowed(cmd: Command[object]) -> bool:
    """What a client that may only watch (``motorbus serve --watch-only``) may send:
    reads, and the stops (a watcher may always stop a device, never start one or change
    a setting).  LA: status query, pause, e-stop, table and register reads; project
    stepper: stop project, manual stop, project and input reads; quad: stop, stop all."""
    if cmd.starts_motion:
        return False
    if is_stop(cmd):
        return True
    if isinstance(cmd, la.Control):
        return cmd.action is la.ControlAction.QUERY_STATUS
    if isinstance(cmd, la.ReadTable | la.ReadRegister):
        return True
    if cmd.family is Family.PROJECT_STEPPER:
        from motorbus.protocol import project_stepper as ps

        return isinstance(cmd, ps.ReadProject | ps.ReadInput)
    return False


def motion_keys(cmd: Command[object]) -> tuple[str, ...]:
    """The devices a motion command moves: its own key, or each entry of an LA broadcast
    (F2/F3).  An LA command to ID 255 answers ``("la:255",)``: every LA on the bus."""
    if isinstance(cmd, la.Broadcast):
        return tuple([_LA_KEYS[ident] for ident, _ in cmd.entries])
    return (cmd.device_key,)


def covers(sent: Command[object], safe: Command[object]) -> bool:
    """True if ``sent`` brings its device at least as far as the safe command ``safe``.

    The same command covers itself; an LA e-stop covers a pause (not the other way
    round), a control frame to ID 255 covers every actuator's, and the quad's stop all
    covers each motor's stop.
    """
    if sent == safe:
        return True
    if sent.family is Family.QUAD_STEPPER:
        from motorbus.protocol import quad_stepper as q

        if isinstance(sent, q.StopAll) and isinstance(safe, q.Stop):
            return True
    if isinstance(sent, la.Control) and isinstance(safe, la.Control):
        return (sent.id in (safe.id, la.BROADCAST_ID)) and safe.action in _LA_STOPS.get(
            sent.action, frozenset()
        )
    return False


def is_stop(cmd: Command[object]) -> bool:
    """True for a command that stops its device: an LA pause or e-stop, a project
    stop or manual stop, a quad motor's stop or stop all."""
    if isinstance(cmd, la.Control):  # (a served bus's tapped copy too: a subclass)
        return cmd.action in _LA_STOPS
    if cmd.family is Family.PROJECT_STEPPER:
        from motorbus.protocol import project_stepper as ps

        return isinstance(cmd, ps.StopProject | ps.ManualStop)
    if cmd.family is Family.QUAD_STEPPER:
        from motorbus.protocol import quad_stepper as q

        return isinstance(cmd, q.Stop | q.StopAll)
    return False


def latch_change(cmd: Command[object]) -> bool | None:
    """What ``cmd`` does to an LA's e-stop latch (manual 3.5.4: after an e-stop, position
    commands are ignored until "work"; a pause would lift it): True sets it (an e-stop),
    False clears it (a "work"), None leaves it (anything else)."""
    if isinstance(cmd, la.Control):
        if cmd.action is la.ControlAction.ESTOP:
            return True
        if cmd.action is la.ControlAction.WORK:
            return False
    return None


def escalated(cmd: Command[object], latched: Container[str]) -> Command[object]:
    """A safe command as it must go to a device whose e-stop latch is set (``latched``
    holds its key, or ``"la:255"``: an e-stop to every LA before any was known): an LA
    pause becomes an e-stop, which keeps the latch where the pause would lift it.  Any
    other command is returned as it is."""
    if (
        isinstance(cmd, la.Control)
        and cmd.action is la.ControlAction.PAUSE
        and (cmd.device_key in latched or _LA_KEYS[la.BROADCAST_ID] in latched)
    ):
        return la.Control(cmd.id, la.ControlAction.ESTOP)
    return cmd


def pending_after(
    sent: Command[object], pending: Iterable[Command[object]]
) -> tuple[Command[object], ...]:
    """The safe commands of ``pending`` that ``sent`` does not cover."""
    return tuple(p for p in pending if not covers(sent, p))
