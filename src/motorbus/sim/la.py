"""A simulated Inspire LA linear actuator (doc 002, docs/protocols.md part C).

Pure: no clock, no I/O.  Every entry point takes ``now`` in seconds on the host's clock.

What the model does (behaviour from the manual; the numbers marked "model choice" are ours):

* A control table (256 bytes, one per index value) in RAM and a simulated flash (C.5).
  ``SAVE`` copies RAM to flash; :meth:`LAModel.power_cycle` reloads RAM from flash.  An ID
  write takes effect at once; a baud write becomes the active rate (``model.baud``) only
  after save and a power cycle (manual 3.6, index 12).  Writes to the read-only registers
  and the table header are ignored; an ID write outside 1..254 is ignored.
* Positioning (0x21, 0x03, a write of the target register, F2 broadcast) moves toward the
  target with a trapezoidal profile (``stroke_speed`` units/s, ``accel`` units/s^2).  Follow
  (0x20, 0x19, F3) tracks the latest streamed target at up to ``stroke_speed``.
* Work / e-stop / pause as manual 3.5.4: after ESTOP position commands are ignored (target
  not adopted, no motion) until WORK; PAUSE stops the motor and the next position command
  resumes directly.  Power-on state: working.
* Faults as manual 3.8, injected with :meth:`LAModel.trigger_fault`: stall and over-current
  stop the motor and auto-clear after 5 s; the third trip in a row latches until
  CLEAR_FAULT; over-temperature stops the motor until the temperature (cooling at
  ``cooling_rate``) falls below the recovery temperature, and CLEAR_FAULT cannot clear it.
  While stall, over-current or over-temperature is active, position commands are ignored.
* Motor abnormal is a *notice* (manual 3.8: "提示"): it does not stop the motor.  It clears
  on CLEAR_FAULT or once the motor draws more than 30 mA, i.e. when the model moves.
* ``seized=True`` models a dead actuator: it takes and answers every command but its
  position never changes, and it reports no fault (what a test rig must fail).
* Nothing answers ID 255, broadcasts, 0x03 or 0x19; a frame ``decode_request`` refuses is
  ignored and counted in ``ignored``.

Where it lives: this module is the device (requests, power states, faults, temperature,
replies); the control table's RAM and flash storage is ``motorbus.sim.la_table``, and
the motor's motion (positioning profile, follow, lag, dead band) ``motorbus.sim.la_motion``.
"""

from __future__ import annotations

import enum
import functools
import math
import random
from typing import ClassVar, Literal

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import LA_REPLY_HEADER, Command, Family, check_int
from motorbus.protocol.la import (
    BROADCAST_ID,
    CMD_CONTROL,
    CMD_READ,
    CMD_WRITE,
    ID_MAX,
    ID_MIN,
    POSITION_MAX,
    POSITION_MIN,
    REPORTED_POSITION_MAX,
    REPORTED_POSITION_MIN,
    BaudCode,
    Broadcast,
    BroadcastMode,
    Control,
    ControlAction,
    ErrorFlags,
    Follow,
    MoveTo,
    ReadRegister,
    ReadTable,
    Register,
    Status,
    WriteRegister,
    WriteTable,
    build_frame,
    decode_request,
)

# SIM_STEP_S, TABLE_BYTES and TABLE_HEADER were defined here; they stay importable from here.
from motorbus.sim.la_motion import SIM_STEP_S as SIM_STEP_S
from motorbus.sim.la_motion import LAMotion
from motorbus.sim.la_table import ID_INDEX, ControlTable
from motorbus.sim.la_table import TABLE_BYTES as TABLE_BYTES
from motorbus.sim.la_table import TABLE_HEADER as TABLE_HEADER
from motorbus.sim.model import DeviceModel

__all__ = [
    "AUTO_CLEAR_S",
    "CONSECUTIVE_WINDOW_S",
    "FAULT_KINDS",
    "LAModel",
    "PowerState",
]

#: Stall and over-current auto-clear 5 s after they trip (manual 3.6 index 32, 3.8).
AUTO_CLEAR_S = 5.0
#: After this many auto-clears in a row, the next stall/over-current latches (manual 3.8:
#: "the third fault can only be cleared with 0x1E").
AUTO_CLEARS_BEFORE_LATCH = 2
#: Model choice: a trip counts as "consecutive" when it occurs within this many seconds
#: after the previous auto-clear.  The manual does not give a window (C.7, A2-18).
CONSECUTIVE_WINDOW_S = 10.0
#: Motor abnormal clears once the measured current exceeds 30 mA (manual 3.8).
MOTOR_ABNORMAL_CLEAR_MA = 30
#: Model choice: current drawn while moving, holding and disabled, in mA.
MOVING_CURRENT_MA = 300
HOLDING_CURRENT_MA = 20
#: Model choice: how far above the limit an injected over-temperature puts the motor, degC.
OVER_TEMPERATURE_OVERSHOOT_C = 5.0
#: Model choice: raw force ADC reading at zero load, and grams per ADC count (12-bit, A2-07).
RAW_FORCE_ZERO_COUNTS = 2048
GRAMS_PER_COUNT = 10
RAW_FORCE_MAX = 4095
#: Model choice: default speed (full 2000-unit stroke in 1.0 s at cruise) and acceleration.
DEFAULT_STROKE_SPEED = 2000.0
DEFAULT_ACCEL = 20000.0
#: Model choice: default cooling rate of the motor, degC per second.
DEFAULT_COOLING_RATE = 1.0
#: Reply latency: 120 us typical, up to 800 us when a control task interrupts (manual 3.4.2).
TURNAROUND_TYPICAL_S = 120e-6
TURNAROUND_MAX_S = 800e-6
#: Fault kinds accepted by :meth:`LAModel.trigger_fault`.
FAULT_KINDS = ("stall", "over_current", "over_temperature", "motor_abnormal")
_TRIP_FLAGS = {"stall": ErrorFlags.STALL, "over_current": ErrorFlags.OVER_CURRENT}

WriteReply = Literal["status", "ack"]
IdChangeReply = Literal["old", "new"]


@functools.lru_cache(maxsize=256)
def _decode_shared(request: bytes) -> Command[object]:
    """``decode_request``, memoised: every model on a bus sees the same frame, and a
    decoded command is an immutable value, so the bus's 15 actuators decode it once."""
    return decode_request(request)


class PowerState(enum.Enum):
    """The power-stage state of manual 3.5.4."""

    WORKING = "working"  # enabled (power-on state, and after WORK)
    ESTOPPED = "estopped"  # disabled; position commands ignored until WORK
    PAUSED = "paused"  # disabled; the next position command resumes


def _choice(field: str, value: object, allowed: tuple[object, ...]) -> object:
    if value not in allowed:
        shown = ", ".join(repr(a) for a in allowed)
        raise LocalProtocolError(
            f"{field}={value!r} is not allowed: choose one of {shown}", field=field, value=value
        )
    return value


def _not_negative(field: str, value: object) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value < 0
    ):
        raise LocalProtocolError(
            f"{field} must be a number >= 0, got {value!r}", field=field, value=value
        )
    return float(value)


def _positive(field: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
        raise LocalProtocolError(
            f"{field} must be a positive number, got {value!r}", field=field, value=value
        )
    return float(value)


class LAModel(DeviceModel):
    """One simulated LA actuator on the bus (see the module docstring for its behaviour).

    Attributes:
        received: every target addressed to this actuator, ``(time, cmd code, target)``,
            including targets it ignored (cmd code 0x02 for a target-register write,
            0xF2/0xF3 for broadcasts).
        ignored: number of frames refused by ``decode_request``.
        silenced: replies not sent because of ``silent_replies``.
        load_g: the load on the force sensor in grams (tests set it).
        ambient: the temperature the motor cools toward, degC.
        temperature: the present motor temperature, degC.
    """

    family: ClassVar[Family] = Family.LA

    def __init__(
        self,
        id: int = 1,
        *,
        stroke_speed: float = DEFAULT_STROKE_SPEED,
        accel: float = DEFAULT_ACCEL,
        write_reply: str = "status",
        status_cmd_echo: str = "0x04",
        id_change_reply: str = "old",
        turnaround_typical: float = TURNAROUND_TYPICAL_S,
        turnaround_max: float = TURNAROUND_MAX_S,
        slow_turnaround_probability: float = 0.02,
        baud_code: int = BaudCode.B921600,
        temperature: float = 25.0,
        force_sensor: bool = True,
        cooling_rate: float = DEFAULT_COOLING_RATE,
        position: float = 0.0,
        silent_replies: int = 0,
        dead_time: float = 0.0,
        lag_tau: float = 0.0,
        dead_band: float = 0.0,
        position_noise: float = 0.0,
        seized: bool = False,
        seed: int | None = None,
        travel_min: float = POSITION_MIN,
        travel_max: float = POSITION_MAX,
    ) -> None:
        """Create an actuator in its power-on state with the factory control table.

        Args:
            id: actuator ID 1..254.
            stroke_speed: top speed in position units per second.
            accel: acceleration of positioning moves in units per second squared.
            write_reply: answer writes with the 22-byte ``"status"`` or the short ``"ack"``
                (A2-03).
            status_cmd_echo: status B4 is ``"0x04"`` (also accepted: 4) or the
                ``"request"``'s command (A2-04).
            id_change_reply: an ID write is answered from the ``"old"`` or ``"new"`` ID (A2-12).
            turnaround_typical: usual reply latency, seconds.
            turnaround_max: worst reply latency, seconds.
            slow_turnaround_probability: chance (0..1) that a reply takes a random latency up
                to ``turnaround_max``.
            baud_code: the ``BaudCode`` in the factory table (0..3).
            temperature: ambient and initial motor temperature, degC.
            force_sensor: LAF/LASF model with a force sensor (else force reads 0).
            cooling_rate: cooling of an overheated motor, degC per second.
            position: initial position, 0..2000.
            silent_replies: the first this many replies are not sent (model choice: an
                actuator that misses its first queries, e.g. still starting up); the
                requests still take effect.  Counted in ``silenced``.
            dead_time: seconds between a position command's arrival and the motor
                acting on it (model choice for test rigs; the target register changes
                at once).
            lag_tau: time constant, seconds, of a first-order lag between follow-mode
                targets and the position the motor chases (0: none).
            dead_band: units; a move stops this far short of its target, measured
                along the approach (half on each side: approaches from below and
                above end ``dead_band`` apart, a simulated backlash).
            position_noise: standard deviation, units, of gaussian noise added to the
                reported position (not to the motion).
            seized: the motor never moves (model choice: a seized gearbox or an
                unplugged motor that the electronics do not notice).  Position
                commands are taken as usual (the target register changes, replies
                are normal, no fault is reported) but the position stays where it is.
            seed: seed of the noise (None: a fixed default, so runs repeat).
            travel_min: a mechanical end stop inside 0..2000 (model choice, for
                calibration): the motor stops there and, pushed on, stalls.
            travel_max: the other end stop, above ``travel_min``.

        Raises:
            LocalProtocolError: a value out of range or not one of the choices.
        """
        check_int("id", id, ID_MIN, ID_MAX)
        vmax = _positive("stroke_speed", stroke_speed)
        accel = _positive("accel", accel)
        self._write_reply_kind = _choice("write_reply", write_reply, ("status", "ack"))
        echo = _choice("status_cmd_echo", status_cmd_echo, ("0x04", CMD_CONTROL, "request"))
        self._echo_request = echo == "request"
        self._id_change_reply = _choice("id_change_reply", id_change_reply, ("old", "new"))
        self._turnaround_typical = _positive("turnaround_typical", turnaround_typical)
        self._turnaround_max = max(
            self._turnaround_typical, _positive("turnaround_max", turnaround_max)
        )
        if not 0.0 <= slow_turnaround_probability <= 1.0:
            raise LocalProtocolError(
                f"slow_turnaround_probability={slow_turnaround_probability!r} is out of range: "
                "allowed 0..1",
                field="slow_turnaround_probability",
                value=slow_turnaround_probability,
            )
        self._slow_probability = float(slow_turnaround_probability)
        check_int("baud_code", baud_code, BaudCode.B19200, BaudCode.B921600)
        self._cooling_rate = _positive("cooling_rate", cooling_rate)
        if not POSITION_MIN <= position <= POSITION_MAX:
            raise LocalProtocolError(
                f"position={position!r} is out of range: allowed {POSITION_MIN}..{POSITION_MAX}",
                field="position",
                value=position,
            )
        self.force_sensor = bool(force_sensor)
        self.ambient = float(temperature)
        self.temperature = float(temperature)
        self.load_g = 0
        self.received: list[tuple[float, int, int]] = []
        self.ignored = 0
        self._silent_left = check_int("silent_replies", silent_replies, 0, 1_000_000)
        self.silenced = 0

        #: The control table (RAM and flash).
        self._table = ControlTable(id=id, baud_code=baud_code, target=round(position))
        self._active_baud = BaudCode(baud_code)

        self._dead_time = _not_negative("dead_time", dead_time)
        #: The motor: position, velocity and the target it drives toward.
        self._motion = LAMotion(
            position=position,
            vmax=vmax,
            accel=accel,
            lag_tau=_not_negative("lag_tau", lag_tau),
            dead_band=_not_negative("dead_band", dead_band),
        )
        self._noise = _not_negative("position_noise", position_noise)
        self._seized = bool(seized)
        self._travel = (_not_negative("travel_min", travel_min), float(travel_max))
        if not self._travel[0] < self._travel[1] <= POSITION_MAX:
            raise LocalProtocolError(
                f"travel_max={travel_max!r} is out of range: allowed travel_min..{POSITION_MAX}",
                field="travel_max",
                value=travel_max,
            )
        self._rng = random.Random(0 if seed is None else seed)
        # Position commands not yet acted on (dead time): (time due, target, follow).
        self._pending: list[tuple[float, int, bool]] = []
        self._time: float | None = None
        self._power = PowerState.WORKING
        self._force_offset = 0
        self._trips: dict[ErrorFlags, tuple[float, bool]] = {}  # flag -> (since, latched)
        self._auto_clears = 0
        self._last_auto_clear: float | None = None
        self._over_temperature = False
        self._motor_abnormal = False

    # --- public view ---------------------------------------------------------------------

    @property
    def id(self) -> int:
        """The ID the actuator answers to now (RAM index 2)."""
        return self._table.ram[ID_INDEX]  # read on every frame: no property call

    @property
    def baud(self) -> int:
        """The active bit rate in bit/s (changes only after save and a power cycle)."""
        return self._active_baud.baud

    @property
    def power_state(self) -> PowerState:
        """Working, e-stopped or paused (manual 3.5.4)."""
        return self._power

    @property
    def position(self) -> int:
        """The position as the status reports it, -20..2020."""
        return min(REPORTED_POSITION_MAX, max(REPORTED_POSITION_MIN, round(self._motion.position)))

    @property
    def target(self) -> int:
        """The target register (index 55)."""
        return self._table.get(Register.TARGET)

    @property
    def moving(self) -> bool:
        """True while the motor is driving toward a target."""
        return self._motion.moving

    @property
    def errors(self) -> ErrorFlags:
        """The fault flags the status reports (B15)."""
        flags = ErrorFlags(0)
        for flag in self._trips:
            flags |= flag
        if self._over_temperature:
            flags |= ErrorFlags.OVER_TEMPERATURE
        if self._motor_abnormal:
            flags |= ErrorFlags.MOTOR_ABNORMAL
        return flags

    @property
    def current(self) -> int:
        """The motor current in mA the status reports."""
        if self.moving:
            return MOVING_CURRENT_MA
        if self._power is PowerState.WORKING and not self._blocked and not self._motor_abnormal:
            return HOLDING_CURRENT_MA
        return 0

    @property
    def force(self) -> int:
        """The force in grams the status reports (0 without a force sensor)."""
        if not self.force_sensor:
            return 0
        return max(-0x8000, min(0x7FFF, self.load_g - self._force_offset))

    def register(self, reg: Register) -> int:
        """Return the value of ``reg`` as a read would return it."""
        self._refresh_live()
        return self._table.get(reg)

    def set_register(self, reg: Register, value: int) -> None:
        """Put ``value`` into RAM directly, bypassing every check and side effect (tests).

        Raises:
            LocalProtocolError: ``value`` does not fit the register's size.
        """
        self._table.put(reg, value)

    def status(self, now: float) -> Status:
        """Advance to ``now`` and return the status the actuator would report."""
        self._advance(now)
        return self._status_value(self.id, CMD_CONTROL, ControlAction.QUERY_STATUS)

    def trigger_fault(self, kind: str, now: float) -> None:
        """Make a fault occur at ``now`` (manual 3.8).

        Args:
            kind: ``"stall"``, ``"over_current"``, ``"over_temperature"`` or
                ``"motor_abnormal"``.
            now: time in seconds.

        Raises:
            LocalProtocolError: unknown kind.
        """
        _choice("kind", kind, FAULT_KINDS)
        self._advance(now)
        if kind in _TRIP_FLAGS:
            recent = (
                self._last_auto_clear is not None
                and now - self._last_auto_clear <= CONSECUTIVE_WINDOW_S
            )
            if not recent:
                self._auto_clears = 0
            latched = self._auto_clears >= AUTO_CLEARS_BEFORE_LATCH
            self._trips[_TRIP_FLAGS[kind]] = (now, latched)
            self._stop()
        elif kind == "over_temperature":
            limit = self._table.get(Register.OVER_TEMPERATURE_LIMIT) / 10
            self.temperature = max(self.temperature, limit + OVER_TEMPERATURE_OVERSHOOT_C)
            self._check_temperature()
        else:
            self._motor_abnormal = True

    # --- DeviceModel -----------------------------------------------------------------------

    def handle(self, request: bytes, now: float) -> list[bytes]:
        """Process one request frame received at ``now``; return the reply frames.

        Refused frames are counted in ``ignored``; frames for other IDs, broadcasts and the
        no-reply commands return ``[]``; so do the first ``silent_replies`` replies.
        """
        replies = self._handle(request, now)
        if replies and self._silent_left:
            self._silent_left -= 1
            self.silenced += 1
            return []
        return replies

    def _handle(self, request: bytes, now: float) -> list[bytes]:
        try:
            cmd = _decode_shared(request)
        except RemoteProtocolError:
            self.ignored += 1
            return []
        self._advance(now)
        if isinstance(cmd, Broadcast):
            follow = cmd.mode is BroadcastMode.FOLLOW
            me = self.id
            for ident, pos in cmd.entries:
                if ident == me:
                    self._position_command(now, int(cmd.mode), pos, follow=follow)
            return []
        addressed = (MoveTo, Follow, Control, ReadRegister, ReadTable, WriteRegister, WriteTable)
        if not isinstance(cmd, addressed):  # pragma: no cover - decode_request gives no other
            return []
        if cmd.id not in (self.id, BROADCAST_ID):
            return []
        answer = cmd.id != BROADCAST_ID
        if isinstance(cmd, MoveTo | Follow):
            self._position_command(now, cmd.cmd, cmd.position, follow=isinstance(cmd, Follow))
            return (
                [self._status(cmd.cmd, ControlAction.QUERY_STATUS)] if cmd.reply and answer else []
            )
        if isinstance(cmd, Control):
            self._control(cmd.action)
            return [self._status(CMD_CONTROL, cmd.action)] if answer else []
        if isinstance(cmd, ReadRegister | ReadTable):
            read = cmd.as_table if isinstance(cmd, ReadRegister) else cmd
            return [self._read(read)]
        if isinstance(cmd, WriteRegister | WriteTable):
            write = cmd.as_table if isinstance(cmd, WriteRegister) else cmd
            reply_id = self._write(now, write)
            return [self._write_reply(reply_id, write.index)] if answer else []
        return []  # pragma: no cover - unreachable, every addressed type is handled above

    def poll(self, now: float) -> list[bytes]:
        """Advance the motion and fault timers to ``now``; the LA sends nothing unsolicited."""
        self._advance(now)
        return []

    def turnaround(self, rng: random.Random) -> float:
        """Reply latency: typical, or with ``slow_turnaround_probability`` up to the max."""
        if rng.random() < self._slow_probability:
            return rng.uniform(self._turnaround_typical, self._turnaround_max)
        return self._turnaround_typical

    def power_cycle(self, now: float) -> None:
        """Power off and on: RAM reloads from flash, the new baud becomes active, the motor
        stops, faults reset (an overheated motor stays hot and faulted)."""
        self._advance(now)
        self._table.reload()
        if not ID_MIN <= self._table.get(Register.ID) <= ID_MAX:
            self._table.put(Register.ID, ID_MIN)
        code = self._table.get(Register.BAUD)
        if code in {c.value for c in BaudCode}:
            self._active_baud = BaudCode(code)
        self._power = PowerState.WORKING
        self._stop()
        # The actuator does not run to a stale saved target at power-on.
        self._table.put(Register.TARGET, min(POSITION_MAX, max(POSITION_MIN, self.position)))
        self._trips.clear()
        self._auto_clears = 0
        self._last_auto_clear = None
        self._motor_abnormal = False
        self._force_offset = 0

    # --- internals -----------------------------------------------------------------------

    @property
    def _blocked(self) -> bool:
        """True while a fault forbids motion (stall, over-current, over-temperature)."""
        return bool(self._trips) or self._over_temperature

    def _stop(self) -> None:
        self._motion.stop()
        self._pending.clear()

    def _reported_position(self) -> int:
        """The position with the measurement noise, clamped as the status reports it."""
        pos = self._motion.position
        if self._noise:
            pos += self._rng.gauss(0.0, self._noise)
        return min(REPORTED_POSITION_MAX, max(REPORTED_POSITION_MIN, round(pos)))

    def _raw_force(self) -> int:
        if not self.force_sensor:
            return 0
        return min(RAW_FORCE_MAX, max(0, RAW_FORCE_ZERO_COUNTS + self.load_g // GRAMS_PER_COUNT))

    def _refresh_live(self) -> None:
        self._table.put(Register.POSITION, self._reported_position())
        self._table.put(Register.FORCE, self.force)
        self._table.put(Register.RAW_FORCE, self._raw_force())

    def _status(self, request_cmd: int, action: int) -> bytes:
        echo = request_cmd if self._echo_request else CMD_CONTROL
        return self._status_from(self.id, echo, action)

    def _status_from(self, ident: int, echo: int, param2: int) -> bytes:
        return self._status_value(ident, echo, param2).encode()

    def _status_value(self, ident: int, echo: int, param2: int) -> Status:
        return Status(
            id=ident,
            cmd_echo=echo,
            param2=param2,
            target=self.target,
            position=self._reported_position(),
            temperature=max(-128, min(127, round(self.temperature))),
            current=self.current,
            force=self.force,
            errors=self.errors,
            internal1=self._raw_force(),
        )

    def _read(self, cmd: ReadTable) -> bytes:
        self._refresh_live()
        data = self._table.read(cmd.index, cmd.count)
        return build_frame(LA_REPLY_HEADER, bytes((self.id, CMD_READ, cmd.index)) + data)

    def _write_reply(self, ident: int, index: int) -> bytes:
        if self._write_reply_kind == "ack":
            return build_frame(LA_REPLY_HEADER, bytes((ident, CMD_WRITE, index, 0x00)))
        echo = CMD_WRITE if self._echo_request else CMD_CONTROL
        return self._status_from(ident, echo, ControlAction.QUERY_STATUS)

    def _write(self, now: float, cmd: WriteTable) -> int:
        """Apply a table write; return the ID the reply should carry."""
        old_id = self.id
        end = cmd.index + len(cmd.data)
        target = Register.TARGET
        before_target = self._table.raw(target)
        self._table.write(cmd.index, cmd.data)
        if not ID_MIN <= self._table.get(Register.ID) <= ID_MAX:
            self._table.put(Register.ID, old_id)  # the actuator keeps an address it can answer to
        if cmd.index <= Register.FORCE_ZERO.index < end:
            if self._table.get(Register.FORCE_ZERO) == 1:
                self._force_offset = self.load_g
            self._table.put(Register.FORCE_ZERO, 0)
        if cmd.index < target.index + target.size and end > target.index:
            wanted = self._table.get(target)
            self._table.set_raw(target, before_target)
            self._position_command(now, CMD_WRITE, wanted, follow=False)
        return old_id if self._id_change_reply == "old" else self.id

    def _position_command(self, now: float, cmd_code: int, target: int, *, follow: bool) -> None:
        self.received.append((now, cmd_code, target))
        if self._power is PowerState.ESTOPPED or self._blocked:
            return
        if not POSITION_MIN <= target <= POSITION_MAX:
            return  # model choice: an out-of-range target is not adopted
        self._power = PowerState.WORKING
        self._table.put(Register.TARGET, target)
        if self._seized:
            return
        if self._dead_time:
            self._pending.append((now + self._dead_time, target, follow))
        else:
            self._motion.adopt(target, follow)

    def _control(self, action: ControlAction) -> None:
        if action is ControlAction.WORK:
            self._power = PowerState.WORKING
        elif action is ControlAction.ESTOP:
            self._power = PowerState.ESTOPPED
            self._stop()
        elif action is ControlAction.PAUSE:
            self._power = PowerState.PAUSED
            self._stop()
        elif action is ControlAction.SAVE:
            self._refresh_live()
            self._table.save()
        elif action is ControlAction.CLEAR_FAULT:
            self._trips.clear()
            self._auto_clears = 0
            self._last_auto_clear = None
            self._motor_abnormal = False

    def _advance(self, now: float) -> None:
        if self._time is None or now <= self._time:
            self._time = now if self._time is None else self._time
            return
        start = self._time
        self._time = now
        motion = self._motion
        while self._pending and self._pending[0][0] <= now:
            due, target, follow = self._pending.pop(0)
            if motion.goal is not None and motion.moving and due > start:
                motion.integrate(due - start)
            start = max(start, due)
            self._motion.adopt(target, follow)
        if motion.goal is not None and motion.moving:
            motion.integrate(now - start)
            low, high = self._travel
            if not low <= motion.position <= high:  # an end stop: the motor stalls on it
                motion.position = min(max(motion.position, low), high)
                self._trips[ErrorFlags.STALL] = (now, False)
                self._stop()
            if self._motor_abnormal and MOVING_CURRENT_MA > MOTOR_ABNORMAL_CLEAR_MA:
                self._motor_abnormal = False
        for flag, (since, latched) in list(self._trips.items()):
            cleared_at = since + AUTO_CLEAR_S
            if not latched and now >= cleared_at:
                del self._trips[flag]
                self._auto_clears += 1
                self._last_auto_clear = cleared_at
        if self.temperature > self.ambient:
            self.temperature = max(
                self.ambient, self.temperature - self._cooling_rate * (now - start)
            )
        self._check_temperature()

    def _check_temperature(self) -> None:
        limit = self._table.get(Register.OVER_TEMPERATURE_LIMIT) / 10
        recovery = self._table.get(Register.RECOVERY_TEMPERATURE) / 10
        if not self._over_temperature and self.temperature > limit:
            self._over_temperature = True
            self._stop()
        elif self._over_temperature and self.temperature < recovery:
            self._over_temperature = False
