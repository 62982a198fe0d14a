"""The Inspire Robots LA-series micro servo linear actuator as an async device."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

from motorbus.bus.bus import Bus, Priority
from motorbus.errors import LocalProtocolError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import check_choice, check_int

__all__ = ["InspireLA", "scan"]


class InspireLA:
    """One LA actuator on a bus, addressed by its ID.

    Positions are unitless 0..2000 (0..100 % of the stroke, A2-08); currents in mA;
    forces in grams; temperatures in degC (the control table stores 0.1 degC).
    Every method validates its arguments before anything is sent and raises
    ``LocalProtocolError`` (a ``ValueError``) naming the field, value and range.

    Args:
        bus: an open :class:`~motorbus.bus.bus.Bus` carrying ``Family.LA``.
        id: the actuator ID, 1..254.
    """

    def __init__(self, bus: Bus, id: int) -> None:
        self.bus = bus
        self.id = check_int("id", id, la.ID_MIN, la.ID_MAX)

    def __repr__(self) -> str:
        return f"InspireLA(id={self.id}, bus={self.bus.name!r})"

    def safe_stop_commands(self, action: object = "pause") -> list[la.Control]:
        """The commands that bring this actuator to a safe state, as values.

        ``action`` is "pause" (power stage off; the next target resumes), "estop"
        (power stage off until "work") or "hold" (nothing: it keeps its last target).
        """
        name = getattr(action, "value", action)
        if name == "hold":
            return []
        if name not in ("pause", "estop"):
            raise LocalProtocolError(
                f"action={action!r} is not allowed: choose pause, estop or hold", field="action"
            )
        sub = la.ControlAction.ESTOP if name == "estop" else la.ControlAction.PAUSE
        return [la.Control(self.id, sub)]

    async def _control(self, action: la.ControlAction, priority: Priority) -> la.Status:
        status: la.Status = await self.bus.request(la.Control(self.id, action), priority=priority)
        return status

    # -- motion -----------------------------------------------------------------

    async def status(self) -> la.Status:
        """Query the status: target, position, temperature, current, force, error flags."""
        return await self._control(la.ControlAction.QUERY_STATUS, Priority.NORMAL)

    async def move_to(self, position: int, *, reply: bool = True) -> la.Status | None:
        """Positioning move (planned, shortest time) to ``position`` 0..2000.

        With ``reply`` (0x21) returns the status; without (0x03) returns ``None`` as
        soon as the frame is sent.
        """
        result: la.Status | None = await self.bus.request(la.MoveTo(self.id, position, reply))
        return result

    async def follow(self, position: int, *, reply: bool = True) -> la.Status | None:
        """Follow-mode target (0x20 with status, 0x19 without); send at a fixed 10-50 ms rate.

        For streaming, use :mod:`motorbus.streams`, which keeps the rate.
        """
        result: la.Status | None = await self.bus.request(la.Follow(self.id, position, reply))
        return result

    async def enable(self) -> la.Status:
        """ "Work": enable the power stage (needed after an e-stop before moves are obeyed)."""
        return await self._control(la.ControlAction.WORK, Priority.HIGH)

    async def estop(self) -> la.Status:
        """Emergency stop (power stage off); jumps the bus queue.  Call ``enable`` to move again."""
        return await self._control(la.ControlAction.ESTOP, Priority.EMERGENCY)

    async def pause(self) -> la.Status:
        """Pause (power stage off); the next position command resumes directly."""
        return await self._control(la.ControlAction.PAUSE, Priority.HIGH)

    async def save(self) -> la.Status:
        """Copy the RAM control table to flash, so settings survive a power cycle."""
        return await self._control(la.ControlAction.SAVE, Priority.NORMAL)

    async def clear_fault(self) -> la.Status:
        """Clear stall, over-current and motor-abnormal faults (not over-temperature, 3.8)."""
        return await self._control(la.ControlAction.CLEAR_FAULT, Priority.HIGH)

    async def recover(self, target: int | None = None) -> la.Status:
        """The recovery recipe of A2-18: query, clear latched faults, work, re-send the target.

        Args:
            target: position to re-send (default: the target the status reports).

        Returns:
            The status after the final move command.
        """
        status = await self.status()
        clearable = la.ErrorFlags.STALL | la.ErrorFlags.OVER_CURRENT | la.ErrorFlags.MOTOR_ABNORMAL
        if status.errors & clearable:
            await self.clear_fault()
        await self.enable()
        moved = await self.move_to(status.target if target is None else target)
        assert moved is not None
        return moved

    # -- control table ------------------------------------------------------------

    async def read(self, register: la.Register) -> int:
        """Read one documented register and return its value (raw units, see ``Register``)."""
        value: int = await self.bus.request(la.ReadRegister(self.id, register))
        return value

    async def write(self, register: la.Register, value: int) -> la.Status | la.WriteAck:
        """Write one documented register; returns the status or the short ack (A2-03).

        Writing ``TARGET`` also moves the actuator (A2-21); prefer ``move_to``.
        """
        reply: la.Status | la.WriteAck = await self.bus.request(
            la.WriteRegister(self.id, register, value)
        )
        return reply

    async def read_table(self, index: int, count: int) -> bytes:
        """Raw read of ``count`` bytes of the control table from ``index``."""
        reply: la.ReadReply = await self.bus.request(la.ReadTable(self.id, index, count))
        return reply.data

    async def write_table(self, index: int, data: bytes) -> la.Status | la.WriteAck:
        """Raw write of ``data`` at ``index``.  Never write undocumented indexes blindly (A2-19)."""
        reply: la.Status | la.WriteAck = await self.bus.request(la.WriteTable(self.id, index, data))
        return reply

    async def position(self) -> int:
        """Current position, -20..2020 (control table 26)."""
        return await self.read(la.Register.POSITION)

    async def target(self) -> int:
        """Target position, 0..2000 (control table 55)."""
        return await self.read(la.Register.TARGET)

    async def force(self) -> int:
        """Measured force in grams (control table 76; LAF/LASF models only)."""
        return await self.read(la.Register.FORCE)

    async def raw_force(self) -> int:
        """Raw force-sensor ADC reading, nominally 0..4095 (control table 78)."""
        return await self.read(la.Register.RAW_FORCE)

    async def zero_force_sensor(self) -> None:
        """Take the present force reading as zero (control table 31)."""
        await self.write(la.Register.FORCE_ZERO, 1)

    async def over_current_limit(self) -> int:
        """Over-current limit in mA, 300..1500 (control table 32)."""
        return await self.read(la.Register.OVER_CURRENT_LIMIT)

    async def set_over_current_limit(self, milliamps: int) -> None:
        """Set the over-current limit, 300..1500 mA."""
        await self.write(la.Register.OVER_CURRENT_LIMIT, milliamps)

    async def temperature_limits(self) -> tuple[float, float]:
        """(over-temperature limit, recovery temperature) in degC (control table 98, 100)."""
        over = await self.read(la.Register.OVER_TEMPERATURE_LIMIT)
        recovery = await self.read(la.Register.RECOVERY_TEMPERATURE)
        return over / 10, recovery / 10

    async def set_temperature_limits(self, over_c: float, recovery_c: float) -> None:
        """Set both temperature limits in degC, in an order that never passes an invalid pair.

        Args:
            over_c: over-temperature limit, 25.0..80.0 degC.
            recovery_c: recovery temperature, 20.0..75.0 degC, at least 5 degC below.
        """
        over = _tenths("over_c", over_c)
        recovery = _tenths("recovery_c", recovery_c)
        # Validate before reading anything back, so bad input sends nothing.
        la.temperature_limit_writes(self.id, over, recovery, over, recovery)
        current_over = await self.read(la.Register.OVER_TEMPERATURE_LIMIT)
        current_recovery = await self.read(la.Register.RECOVERY_TEMPERATURE)
        for cmd in la.temperature_limit_writes(
            self.id, over, recovery, current_over, current_recovery
        ):
            await self.bus.request(cmd)

    async def baud_code(self) -> la.BaudCode:
        """The baud-rate code stored in the control table (12)."""
        return la.BaudCode(await self.read(la.Register.BAUD))

    async def set_baud_code(self, code: la.BaudCode | int) -> None:
        """Store a new baud code; it takes effect only after ``save`` and a power cycle (A2-13)."""
        check_choice("code", code, [int(c) for c in la.BaudCode], "BaudCode")
        await self.write(la.Register.BAUD, int(code))

    async def change_id(self, new_id: int, *, save: bool = False) -> InspireLA:
        """Give the actuator a new ID (effective at once) and return a handle for it.

        The reply may carry the old or the new ID (A2-12); both are accepted.  With
        ``save`` the change is written to flash so it survives a power cycle.
        """
        check_int("new_id", new_id, la.ID_MIN, la.ID_MAX)
        await self.write(la.Register.ID, new_id)
        moved = InspireLA(self.bus, new_id)
        if save:
            await moved.save()
        return moved


def _tenths(field: str, degrees: object) -> int:
    """A temperature in degC as the table's 0.1 degC integer; refuses non-numbers and NaN."""
    if (
        isinstance(degrees, bool)
        or not isinstance(degrees, int | float)
        or not math.isfinite(degrees)
    ):
        raise LocalProtocolError(
            f"{field} must be a temperature in degC (a finite number), got {degrees!r}",
            field=field,
            value=degrees,
        )
    return round(degrees * 10)


async def scan(
    bus: Bus,
    ids: Iterable[int] = range(la.ID_MIN, la.ID_MAX + 1),
    *,
    timeout: float | None = None,
    progress: Callable[[int, int, bool], None] | None = None,
) -> list[int]:
    """Find the LA actuators that answer a status query on ``bus``.

    Args:
        bus: an open bus carrying ``Family.LA``.
        ids: the IDs to try (default 1..254).
        timeout: per-ID reply budget in seconds (default: the bus's deadline).
        progress: called after each ID as ``progress(id, total, found)``.

    Returns:
        The IDs that answered, in ascending order.
    """
    candidates = [check_int("id", i, la.ID_MIN, la.ID_MAX) for i in ids]
    found: list[int] = []
    for i in candidates:
        try:
            await bus.request(
                la.Control(i, la.ControlAction.QUERY_STATUS),
                timeout=timeout,
                retries=0,
                priority=Priority.BACKGROUND,
            )
        except ReplyTimeoutError:
            hit = False
        else:
            hit = True
            found.append(i)
        if progress is not None:
            progress(i, len(candidates), hit)
    return found
