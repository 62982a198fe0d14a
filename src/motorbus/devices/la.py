"""The Inspire Robots LA-series micro servo linear actuator as an async device."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from motorbus.bus.bus import Bus, Priority
from motorbus.devices.calibration import Calibration, check_device_name

# The scan has a module of its own (documented there); its names stay importable here.
from motorbus.devices.la_scan import ScanPass as ScanPass
from motorbus.devices.la_scan import ScanReport as ScanReport
from motorbus.devices.la_scan import scan as scan
from motorbus.errors import ArrivalTimeoutError, LocalProtocolError, ReplyTimeoutError
from motorbus.protocol import la, safety
from motorbus.protocol.base import check_choice, check_flag, check_int, check_timeout
from motorbus.validation import check_device_bus

__all__ = ["ArrivalTimeoutError", "InspireLA"]

#: ``move_to(wait=True)`` defaults: within 10 units (0.5 % of the stroke), 10 s, a
#: status query every 20 ms; and the largest values allowed.
ARRIVAL_TOLERANCE = 10
ARRIVAL_TOLERANCE_MAX = 200
ARRIVAL_TIMEOUT_S = 10.0
ARRIVAL_TIMEOUT_MAX_S = 600.0
ARRIVAL_POLL_S = 0.02
ARRIVAL_POLL_MAX_S = 10.0


class InspireLA:
    """One LA actuator on a bus, addressed by its ID.

    Positions are unitless 0..2000 (0..100 % of the stroke, A2-08); currents in mA;
    forces in grams; temperatures in degC (the control table stores 0.1 degC).
    Every method validates its arguments before anything is sent and raises
    ``LocalProtocolError`` (a ``ValueError``) naming the field, value and range.

    Args:
        bus: an open :class:`~motorbus.bus.bus.Bus` carrying ``Family.LA``.
        id: the actuator ID, 1..254.
        stroke_mm: the stroke of this model in millimetres (e.g. 30 for an LA..-30):
            enables :meth:`position_mm`, :meth:`move_to_mm`, :meth:`to_mm` and
            :meth:`from_mm` (0..2000 maps linearly to 0..stroke_mm).  The actuator
            cannot report its stroke; the 0..2000 API is the same with or without it.
        calibration: units, soft limits, direction, offset (``Calibration``; a bus file's
            named devices have theirs); ``stroke_mm`` replaces its stroke.
        name: the device's name (default ``"la:ID"``), in errors and ``BusManager.device``.
    """

    def __init__(
        self,
        bus: Bus,
        id: int,
        *,
        stroke_mm: float | None = None,
        calibration: Calibration | None = None,
        name: str | None = None,
    ) -> None:
        check_device_bus(bus)
        self.bus = bus
        self.id = check_int("id", id, la.ID_MIN, la.ID_MAX)
        cal = Calibration() if calibration is None else calibration
        if not isinstance(cal, Calibration):
            raise LocalProtocolError(f"calibration={cal!r}: not a Calibration", field="calibration")
        if stroke_mm is not None:
            cal = dataclasses.replace(cal, stroke_mm=stroke_mm)  # checked there
        #: Units, soft limits, stroke (``motorbus.devices.calibration``): every move is
        #: checked against the limits before anything is sent.
        self.calibration = cal
        #: The name a bus file gives it (``BusManager.device(name)``), else ``"la:ID"``.
        self.name = self.key if name is None else check_device_name("name", name)

    def __repr__(self) -> str:
        return f"InspireLA(id={self.id}, bus={self.bus.name!r})"

    # -- units (raw 0..2000, mm, percent of the calibrated range) ---------------------

    @property
    def stroke_mm(self) -> float | None:
        """The stroke of this model in millimetres (``None``: not given)."""
        return self.calibration.stroke_mm

    @property
    def unit(self) -> str:
        """The unit of positions given without one: ``raw`` unless calibrated otherwise."""
        return self.calibration.unit

    def to_unit(self, position: float, unit: str | None = None) -> float:
        """A raw position 0..2000 in ``unit`` ("raw", "mm", "percent"; default :attr:`unit`)."""
        return self.calibration.from_raw(position, unit, device=self.name)

    def from_unit(self, value: float, unit: str | None = None) -> int:
        """``value`` in ``unit`` (default :attr:`unit`) as a raw position, checked against
        the soft limits (``LocalProtocolError`` naming the device, value and limits)."""
        return self.calibration.to_raw(value, unit, device=self.name, whole=True)

    def to_mm(self, position: float) -> float:
        """A position in 0..2000 units as millimetres (needs ``stroke_mm``)."""
        return self.to_unit(position, "mm")

    def from_mm(self, mm: float) -> int:
        """Millimetres as the nearest position unit, within the soft limits (needs
        ``stroke_mm``)."""
        return self.from_unit(mm, "mm")

    async def position_in(self, unit: str | None = None) -> float:
        """The current position in ``unit`` (default :attr:`unit`), from a status query."""
        self.calibration.limits_in(
            unit, device=self.name
        )  # a bad unit fails before anything is sent
        return self.to_unit((await self.status()).position, unit)

    async def position_mm(self) -> float:
        """The current position in millimetres, from a status query (needs ``stroke_mm``)."""
        return await self.position_in("mm")

    async def move_to_mm(self, mm: float, **kwargs: Any) -> la.Status | None:
        """:meth:`move_to` with the target in millimetres; ``tolerance`` stays raw."""
        return await self.move_to(mm, unit="mm", **kwargs)

    def safe_stop_commands(self, action: object = "pause") -> list[la.Control]:
        """The commands that bring this actuator to a safe state, as values.

        ``action`` is "pause" (power stage off; the next target resumes), "estop"
        (power stage off until "work") or "hold" (nothing: it keeps its last target).
        """
        commands = safety.safe_stop_commands(self.key, action)
        return [cmd for cmd in commands if isinstance(cmd, la.Control)]

    @property
    def key(self) -> str:
        """This actuator's device key, ``"la:ID"`` (stats, leases)."""
        return f"la:{self.id}"

    async def release(self, *, hold: bool = False) -> None:
        """End the program's hold on this actuator (moved outside any lease).

        Every move (``move_to``, ``follow``, a target write) sent outside an explicit
        lease (``bus.lease``) is owned by the bus's implicit lease, and the bus applies
        its safe action (pause, by default) when it closes.  ``release()`` applies it
        now; ``release(hold=True)`` ends the ownership on purpose and sends nothing: the
        actuator keeps its target, also after the bus closes.

        Raises:
            LeaseConflictError: an explicit lease holds the actuator (release that).
        """
        await self.bus.release([self.key], hold=hold)

    async def _control(self, action: la.ControlAction, priority: Priority) -> la.Status:
        status = await self.bus.request(la.control_frame(self.id, action), priority=priority)
        return status

    # -- motion -----------------------------------------------------------------

    async def status(self) -> la.Status:
        """Query the status: target, position, temperature, current, force, error flags."""
        return await self._control(la.ControlAction.QUERY_STATUS, Priority.NORMAL)

    async def move_to(
        self,
        position: float,
        *,
        unit: str | None = None,
        reply: bool = True,
        wait: bool = False,
        tolerance: int = ARRIVAL_TOLERANCE,
        timeout: float = ARRIVAL_TIMEOUT_S,
        poll_interval: float = ARRIVAL_POLL_S,
    ) -> la.Status | None:
        """Positioning move (planned, shortest time) to ``position`` 0..2000.

        With ``reply`` (0x21) returns the status; without (0x03) returns ``None`` as
        soon as the frame is sent.

        The move is owned (``motorbus.bus.leases``): by the running task's lease, else
        by the bus's implicit lease, and the actuator gets its safe action (pause) when
        the bus closes, unless released first with ``await la.release(hold=True)``.

        The LA has no "in position" flag: its status reports only target and position.
        With ``wait=True`` the move is followed by status queries every
        ``poll_interval`` seconds until the reported position is within ``tolerance``
        of ``position`` on two queries in a row (arrived and not passing through), and
        the last status is returned.  The wait does not stop the actuator on a timeout.

        Args:
            position: the target in ``unit``: raw 0..2000 (0..100 % of the stroke) by
                default, within the soft limits of :attr:`calibration`.
            unit: "raw", "mm" or "percent" (default :attr:`unit`, raw unless calibrated).
            reply: send 0x21 (with a status reply) rather than 0x03.
            wait: return only once the actuator has arrived (see above).
            tolerance: 0..200 position units (default 10, 0.5 % of the stroke).
            timeout: seconds to wait for arrival after the move, 0..600 (default 10).
            poll_interval: seconds between status queries, 0..10 (default 0.02; the
                bus's 1 ms spacing is the floor).

        Raises:
            LocalProtocolError: a bad argument, before anything is sent.
            ArrivalTimeoutError: ``wait`` and not arrived within ``timeout``; names the
                actuator, the target, the tolerance and the last position reported.
            LeaseConflictError: another owner (a stream, another lease) holds the
                actuator; nothing was sent.
        """
        if type(wait) is not bool:  # "no" is truthy: it must not pick waiting
            check_flag("wait", wait)
        if wait:
            check_int("tolerance", tolerance, 0, ARRIVAL_TOLERANCE_MAX)
            check_timeout("timeout", timeout, ARRIVAL_TIMEOUT_MAX_S)
            check_timeout("poll_interval", poll_interval, ARRIVAL_POLL_MAX_S)
        raw = self.from_unit(position, unit)
        result: la.Status | None = await self.bus.request(la.MoveTo(self.id, raw, reply))
        if wait:
            return await self._wait_arrived(raw, tolerance, timeout, poll_interval)
        return result

    async def _wait_arrived(
        self, target: int, tolerance: int, timeout: float, poll: float
    ) -> la.Status:
        clock = self.bus.timer
        deadline = clock.now() + timeout
        within = 0
        status: la.Status | None = None
        while True:
            status = await self.status()
            within = within + 1 if abs(status.position - target) <= tolerance else 0
            if within >= 2:
                return status
            if clock.now() + poll > deadline:
                raise ArrivalTimeoutError(
                    f"la:{self.id} did not reach {target} (tolerance {tolerance}) within "
                    f"{timeout:g} s: last position {status.position}, target "
                    f"{status.target}, errors {status.errors!r}",
                    id=self.id,
                    target=target,
                    status=status,
                )
            await clock.sleep_until(clock.now() + poll)

    async def follow(
        self, position: float, *, unit: str | None = None, reply: bool = True
    ) -> la.Status | None:
        """Follow-mode target in ``unit`` (as :meth:`move_to`); 0x20 with status, 0x19
        without; send at a fixed 10-50 ms rate (:mod:`motorbus.streams` keeps it)."""
        raw = self.from_unit(position, unit)
        result: la.Status | None = await self.bus.request(la.Follow(self.id, raw, reply))
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

    async def recover(self, target: float | None = None) -> la.Status:
        """The recovery recipe of A2-18: query, clear latched faults, work, re-send the target.

        The target is checked against the soft limits before the actuator is enabled: a
        target that would be refused never leaves an e-stopped actuator powered.

        Args:
            target: position to re-send, in :attr:`unit` (default: the target the
                status reports, in raw units as it reports it).

        Returns:
            The status after the final move command.

        Raises:
            LocalProtocolError: the target (given, or reported) is outside the soft
                limits; only the status query was sent.
        """
        raw = None if target is None else self.from_unit(target)  # before anything is sent
        status = await self.status()
        if raw is None:
            raw = self.from_unit(status.target, "raw")  # before the actuator is enabled
        clearable = la.ErrorFlags.STALL | la.ErrorFlags.OVER_CURRENT | la.ErrorFlags.MOTOR_ABNORMAL
        if status.errors & clearable:
            await self.clear_fault()
        await self.enable()
        moved = await self.move_to(raw, unit="raw")
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
        reply = await self.bus.request(la.ReadTable(self.id, index, count))
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
        """Set the over-current limit, 300..1500 mA (effective now; ``save()`` keeps it)."""
        await self.write(la.Register.OVER_CURRENT_LIMIT, milliamps)

    async def temperature_limits(self) -> tuple[float, float]:
        """(over-temperature limit, recovery temperature) in degC (control table 98, 100)."""
        over = await self.read(la.Register.OVER_TEMPERATURE_LIMIT)
        recovery = await self.read(la.Register.RECOVERY_TEMPERATURE)
        return over / 10, recovery / 10

    async def set_temperature_limits(self, over_c: float, recovery_c: float) -> None:
        """Set both temperature limits in degC, in an order that never passes an invalid pair.

        Effective now, in RAM: ``save()`` keeps them over a power cycle.

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
        check_flag("save", save)  # a truthy text would write the flash
        moved = InspireLA(self.bus, new_id)
        try:
            await self.write(la.Register.ID, new_id)
        except ReplyTimeoutError:
            # The write takes effect at once: if its answer was lost (or came too late),
            # a retry to the old ID can never be answered.  Ask the new ID instead.
            try:
                await moved.status()
            except ReplyTimeoutError:
                raise ReplyTimeoutError(
                    f"la:{self.id} did not confirm the change to ID {new_id}, and la:{new_id} "
                    "does not answer either"
                ) from None
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
