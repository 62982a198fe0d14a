"""A simulated 4-axis "FF AA" stepper controller (doc 001, docs/protocols.md part B).

Pure: no clock, no I/O.  Every entry point takes ``now`` in seconds on the host's clock.

What the model does (the manual gives behaviour, not timing; the numbers are ours):

* Four motors, each with subdivision, step angle, pulse count, direction, start
  frequency, accel and speed.  Parameters live in RAM; ``Save`` copies them to a
  simulated flash and :meth:`QuadStepperModel.power_cycle` reloads them from there.
  Positions, motion, LEDs and pending replies do not survive a power cycle.
* Every valid request is answered with its ack at once (after the turnaround).  A frame
  that :func:`~motorbus.protocol.quad_stepper.decode_request` refuses (unknown command,
  nonzero spare byte, value out of range) is ignored and counted in ``ignored``.
* ``Run`` moves the motor by its pulse count in its direction.  The ack and the done reply
  are ``FF AA 00 09 00 00`` / ``FF AA 00 09 01 00`` as the manual prints them
  (``run_ack_address="zero"``, A1-02) or carry the motor number (``"motor"``).  The done
  reply comes out of :meth:`~QuadStepperModel.poll` when the motion ends.  A ``Run`` for a
  motor that is already moving is acknowledged and otherwise ignored.
* ``RunAll`` starts every motor that is not moving; each motor's completion emits a run done
  reply.  The manual documents no completion for run-all (A1-04): this is our model's
  choice (``run_all_done="each"``); ``run_all_done="none"`` models a controller that sends
  none for the motors run-all started.
* ``Stop`` / ``StopAll`` stop at once, keep the position reached and emit no done reply.
* ``Home`` runs continuously (speed profile below with no end) in the configured direction
  until its stop input (YL1..YL13, set with :meth:`~QuadStepperModel.set_input`) is active,
  then stops and sets the position to 0 (the home point); with stop input 0 it runs until
  stopped (A1-10).  Homing has no done reply in the manual, so none is sent.
* ``SetLed`` acks at once; the LED changes and the done reply ``FF AA 00 0C L 01`` is sent
  ``led_delay_s`` later (default 5 ms).

Kinematic model (documented choice, not from the manual):

* pulses per revolution = subdivision x 360 x 100 / step_angle_x100 (doc 001 section 二);
* cruise rate (pulses/s) = speed_rpm / 60 x pulses per revolution; if that is below the
  start frequency the motor runs at the start frequency, and at least ``MIN_RATE_HZ``;
* the rate starts at the start frequency and ramps linearly to the cruise rate with
  ``accel_hz x ACCEL_SCALE`` Hz per second (we read the accel "frequency" as Hz gained per
  millisecond), then ramps down symmetrically; a short move never reaches cruise (triangle
  profile).  ``accel_hz = 0`` means no ramp: the motor runs at the cruise rate throughout.
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import ClassVar, Literal

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import FF_AA, Family, check_int
from motorbus.protocol.quad_stepper import (
    ADDRESS_IO,
    CMD_LED,
    CMD_RUN,
    FLAG_ACK,
    FLAG_DONE,
    LED_ALL,
    LED_COUNT,
    MOTORS,
    RUN_REPLY_ADDRESS,
    STOP_INPUT_MAX,
    STOP_INPUT_NONE,
    AccelAndSpeed,
    DirectionAndStartFrequency,
    Home,
    MotorSetup,
    QuadCommand,
    RotationDirection,
    Run,
    RunAll,
    RunPulses,
    Save,
    SetLed,
    Stop,
    StopAll,
    decode_request,
)
from motorbus.sim.model import DeviceModel

__all__ = [
    "ACCEL_SCALE",
    "DEFAULT_LED_DELAY_S",
    "DEFAULT_TURNAROUND_S",
    "MIN_RATE_HZ",
    "MotionProfile",
    "MotorParams",
    "MotorState",
    "QuadStepperModel",
]

#: The manual gives no reply latency (A1-09); ~1 ms is a plausible small-MCU figure.
DEFAULT_TURNAROUND_S = 1e-3
#: Delay between an LED ack and its done reply; not in the manual, our choice.
DEFAULT_LED_DELAY_S = 5e-3
#: accel_hz is read as Hz gained per millisecond (the manual gives no unit, A1-06 context).
ACCEL_SCALE = 1000.0
#: Floor of the pulse rate so that a motor set to 0 RPM and 0 Hz still finishes its move.
MIN_RATE_HZ = 1.0
#: Degrees per revolution x 100, the scale of step_angle_x100 (doc 001 section 二 gear ratio).
_DEG_X100_PER_REV = 360 * 100

RunAckAddress = Literal["zero", "motor"]
#: Whether motors started by run-all send a run done reply (A1-04 documents none).
RunAllDone = Literal["each", "none"]


@dataclass(frozen=True, slots=True)
class MotorParams:
    """The parameters of one motor, as set by commands 0x01, 0x03, 0x04 and 0x05.

    The defaults are the model's (the manual gives none); they are the values of the
    documented and synthesized examples: 8 microsteps, 1.8 deg, 50 Hz start, accel 30,
    100 RPM.
    """

    subdivision: int = 8
    step_angle_x100: int = 180
    pulses: int = 0
    direction: RotationDirection = RotationDirection.FORWARD
    start_hz: int = 50
    accel_hz: int = 30
    speed_rpm: int = 100

    @property
    def pulses_per_rev(self) -> float:
        """Motor pulses per revolution (doc 001 section 二: subdivision x 360 x 100 / angle)."""
        return self.subdivision * _DEG_X100_PER_REV / self.step_angle_x100

    def profile(self, pulses: int | None) -> MotionProfile:
        """The speed profile of a move of ``pulses`` (``None`` = run until stopped)."""
        cruise = self.speed_rpm / 60.0 * self.pulses_per_rev
        start = float(self.start_hz)
        cruise = max(cruise, start, MIN_RATE_HZ)
        return MotionProfile(min(start, cruise), cruise, self.accel_hz * ACCEL_SCALE, pulses)


@dataclass(frozen=True, slots=True)
class MotionProfile:
    """A symmetric trapezoidal (or triangular) pulse-rate profile.

    Attributes:
        start_hz: the rate at the start and end of the move, pulses/s.
        cruise_hz: the highest rate, pulses/s (> 0).
        accel_hz_per_s: ramp slope in pulses/s per second; 0 = no ramp.
        pulses: length of the move; ``None`` for a continuous run (homing).
    """

    start_hz: float
    cruise_hz: float
    accel_hz_per_s: float
    pulses: int | None

    def _ramp(self) -> tuple[float, float, float]:
        """Return (ramp time s, ramp pulses, peak rate) of one ramp (up or down)."""
        f0, fc, a = self.start_hz, self.cruise_hz, self.accel_hz_per_s
        if a <= 0 or f0 >= fc or self.pulses == 0:
            return 0.0, 0.0, fc
        t_ramp = (fc - f0) / a
        n_ramp = (f0 + fc) / 2 * t_ramp
        if self.pulses is None or 2 * n_ramp <= self.pulses:
            return t_ramp, n_ramp, fc
        # Too short to reach cruise: ramp up over half the move, then down.
        peak = math.sqrt(f0 * f0 + a * self.pulses)
        return (peak - f0) / a, self.pulses / 2, peak

    def duration(self) -> float:
        """Seconds the move takes; ``math.inf`` for a continuous run."""
        if self.pulses is None:
            return math.inf
        t_ramp, n_ramp, peak = self._ramp()
        return 2 * t_ramp + (self.pulses - 2 * n_ramp) / peak

    def pulses_at(self, elapsed: float) -> int:
        """Whole pulses emitted ``elapsed`` seconds after the start (0..pulses)."""
        if elapsed <= 0:
            return 0
        # Exact at the end, whatever the float rounding on the way: the end time is
        # start + duration, and (start + duration) - start can come out a hair short.
        if self.pulses is not None and elapsed >= self.duration() - _END_TOLERANCE_S:
            return self.pulses
        t_ramp, n_ramp, peak = self._ramp()
        f0, a = self.start_hz, self.accel_hz_per_s
        if elapsed < t_ramp:
            done = f0 * elapsed + a * elapsed * elapsed / 2
        elif self.pulses is None:
            done = n_ramp + peak * (elapsed - t_ramp)
        else:
            t_cruise = (self.pulses - 2 * n_ramp) / peak
            t_down = elapsed - t_ramp - t_cruise
            if t_down <= 0:
                done = n_ramp + peak * (elapsed - t_ramp)
            elif t_down >= t_ramp:
                return self.pulses
            else:
                done = self.pulses - n_ramp + peak * t_down - a * t_down * t_down / 2
        whole = math.floor(done + 1e-9)  # absorb float error at exact phase boundaries
        return whole if self.pulses is None else min(whole, self.pulses)


#: Float slack when deciding that a move has reached its end time.
_END_TOLERANCE_S = 1e-9


@dataclass(slots=True)
class MotorState:
    """One simulated motor (mutable; read it from tests through ``model.motors[n]``).

    Attributes:
        params: the RAM parameters.
        position: signed pulses from power-up (forward +), as of the last call that
            passed ``now`` to the model.
        stop_input: the homing stop input while homing (0 = none), else 0.
    """

    params: MotorParams = field(default_factory=MotorParams)
    position: int = 0
    stop_input: int = STOP_INPUT_NONE
    _profile: MotionProfile | None = None
    _start_time: float = 0.0
    _start_position: int = 0
    _sign: int = 1

    @property
    def running(self) -> bool:
        """True while a run or a homing is in progress (until its end is processed)."""
        return self._profile is not None

    @property
    def homing(self) -> bool:
        """True while homing (a run without end)."""
        return self._profile is not None and self._profile.pulses is None

    @property
    def end_time(self) -> float | None:
        """When the current run ends; ``None`` if idle or homing."""
        if self._profile is None or self._profile.pulses is None:
            return None
        return self._start_time + self._profile.duration()

    def start(self, pulses: int | None, now: float, stop_input: int = STOP_INPUT_NONE) -> None:
        """Begin a run of ``pulses`` (``None`` = homing) at ``now``."""
        self._profile = self.params.profile(pulses)
        self._start_time = now
        self._start_position = self.position
        self._sign = -1 if self.params.direction is RotationDirection.REVERSE else 1
        self.stop_input = stop_input

    def advance(self, now: float) -> None:
        """Update ``position`` to ``now`` without ending the motion."""
        if self._profile is not None:
            moved = self._profile.pulses_at(now - self._start_time)
            self.position = self._start_position + self._sign * moved

    def halt(self, now: float) -> None:
        """Stop at ``now``, keeping the position reached."""
        self.advance(now)
        self._profile = None
        self.stop_input = STOP_INPUT_NONE

    def moving_at(self, now: float) -> bool:
        """True if the motion has not ended by ``now``."""
        end = self.end_time
        return self.running and (end is None or end > now)


class QuadStepperModel(DeviceModel):
    """A simulated 4-axis stepper controller speaking the 9-byte FF AA protocol.

    Args:
        run_ack_address: ``"zero"`` (default, as the manual prints) sends run acks and done
            replies to address 0x00; ``"motor"`` sends them with the motor number (A1-02).
        turnaround_s: seconds from the end of a request to the first reply byte.
        led_delay_s: seconds from an LED ack to its done reply.
        run_all_done: ``"each"`` (default): every motor run-all started sends its run done
            reply; ``"none"``: they send none (A1-04 documents no completion).

    Raises:
        LocalProtocolError: for an unknown ``run_ack_address`` or ``run_all_done``, or a
            negative delay.
    """

    family: ClassVar[Family] = Family.QUAD_STEPPER

    def __init__(
        self,
        *,
        run_ack_address: RunAckAddress = "zero",
        turnaround_s: float = DEFAULT_TURNAROUND_S,
        led_delay_s: float = DEFAULT_LED_DELAY_S,
        run_all_done: RunAllDone = "each",
    ) -> None:
        if run_ack_address not in ("zero", "motor"):
            raise LocalProtocolError(
                f"run_ack_address={run_ack_address!r} is not allowed: choose 'zero' or 'motor'",
                field="run_ack_address",
                value=run_ack_address,
            )
        if run_all_done not in ("each", "none"):
            raise LocalProtocolError(
                f"run_all_done={run_all_done!r} is not allowed: choose 'each' or 'none'",
                field="run_all_done",
                value=run_all_done,
            )
        self.run_all_done: RunAllDone = run_all_done
        for name, value in (("turnaround_s", turnaround_s), ("led_delay_s", led_delay_s)):
            if not value >= 0:
                raise LocalProtocolError(
                    f"{name}={value!r} is out of range: allowed >= 0 seconds",
                    field=name,
                    value=value,
                )
        self.run_ack_address: RunAckAddress = run_ack_address
        self.turnaround_s = turnaround_s
        self.led_delay_s = led_delay_s
        #: Requests refused by decode_request and therefore not answered.
        self.ignored = 0
        self._flash = {m: MotorParams() for m in MOTORS}
        self._inputs: set[int] = set()
        self._reset_ram()

    def _reset_ram(self) -> None:
        self._motors = {m: MotorState(params=self._flash[m]) for m in MOTORS}
        self._leds = [False] * LED_COUNT
        # Pending LED switches: (due time, sequence, LED 1..5, on).
        self._led_ops: list[tuple[float, int, int, bool]] = []
        # Unsolicited frames that are due: (time, sequence, frame).
        self._outbox: list[tuple[float, int, bytes]] = []
        self._seq = 0
        # Motors whose current run was started by run-all and reports no done reply.
        self._silent_runs: set[int] = set()

    # --- read-only views for tests ---------------------------------------------------------

    @property
    def motors(self) -> Mapping[int, MotorState]:
        """The motors keyed by motor number 1..4."""
        return MappingProxyType(self._motors)

    @property
    def leds(self) -> tuple[bool, ...]:
        """LED1..LED4 (index 0 = LED1), True = lit."""
        return tuple(self._leds)

    def saved_params(self, motor: int) -> MotorParams:
        """The parameters of ``motor`` (1..4) in simulated flash."""
        return self._flash[check_int("motor", motor, MOTORS[0], MOTORS[-1])]

    def input_active(self, n: int) -> bool:
        """True if input YL``n`` (1..13) is active."""
        return n in self._inputs

    # --- DeviceModel -----------------------------------------------------------------------

    def turnaround(self, rng: random.Random) -> float:
        """The configured ``turnaround_s`` (fixed: the manual gives no figure, A1-09)."""
        return self.turnaround_s

    def handle(self, request: bytes, now: float) -> list[bytes]:
        """Execute one request received at ``now``; return its ack (or ``[]`` if refused)."""
        try:
            cmd = decode_request(request)
        except RemoteProtocolError:
            self.ignored += 1
            return []
        self._settle(now)
        self._execute(cmd, now)
        if isinstance(cmd, Run):
            return [self._run_reply(cmd.motor, FLAG_ACK)]
        return [_ack_bytes(cmd)]

    def poll(self, now: float) -> list[bytes]:
        """Process everything up to ``now``; return the done replies that became due."""
        self._settle(now)
        due = [item for item in self._outbox if item[0] <= now]
        self._outbox = [item for item in self._outbox if item[0] > now]
        return [frame for _, _, frame in sorted(due)]

    def next_event_time(self) -> float | None:
        """The earliest pending done reply or end of motion, or ``None``."""
        times = [t for t, _, _ in self._outbox]
        times += [t for t, _, _, _ in self._led_ops]
        times += [e for m in self._motors.values() if (e := m.end_time) is not None]
        return min(times, default=None)

    def power_cycle(self, now: float) -> None:
        """Power off and on: RAM parameters reload from flash; motion, LEDs, replies are lost."""
        self._reset_ram()

    # --- test hooks ------------------------------------------------------------------------

    def set_input(self, n: int, active: bool, now: float) -> None:
        """Set input YL``n`` (1..13); activating a motor's homing stop input ends its homing.

        Raises:
            LocalProtocolError: if ``n`` is out of 1..13.
        """
        check_int("n", n, STOP_INPUT_NONE + 1, STOP_INPUT_MAX)
        self._settle(now)
        if active:
            self._inputs.add(n)
            for motor in self._motors.values():
                if motor.homing and motor.stop_input == n:
                    self._home_reached(motor, now)
        else:
            self._inputs.discard(n)

    # --- internals -------------------------------------------------------------------------

    def _push(self, when: float, frame: bytes) -> None:
        self._outbox.append((when, self._seq, frame))
        self._seq += 1

    def _run_reply(self, motor: int, flag: int) -> bytes:
        address = RUN_REPLY_ADDRESS if self.run_ack_address == "zero" else motor
        return _frame(address, CMD_RUN, flag, 0)

    def _settle(self, now: float) -> None:
        """Finish motions and LED switches due by ``now``, queueing their done replies."""
        for number, motor in self._motors.items():
            end = motor.end_time
            if end is not None and end <= now:
                motor.halt(end)
                if number in self._silent_runs:
                    self._silent_runs.discard(number)
                else:
                    self._push(end, self._run_reply(number, FLAG_DONE))
            else:
                motor.advance(now)
        due = sorted(op for op in self._led_ops if op[0] <= now)
        self._led_ops = [op for op in self._led_ops if op[0] > now]
        for when, _, led, on in due:
            targets = range(LED_COUNT) if led == LED_ALL else (led - 1,)
            for i in targets:
                self._leds[i] = on
            self._push(when, _frame(ADDRESS_IO, CMD_LED, led, FLAG_DONE))

    def _home_reached(self, motor: MotorState, now: float) -> None:
        motor.halt(now)
        motor.position = 0  # the stop input marks the home point

    def _execute(self, cmd: QuadCommand, now: float) -> None:
        match cmd:
            case MotorSetup(motor=m, subdivision=sub, step_angle_x100=ang):
                state = self._motors[m]
                state.params = replace(state.params, subdivision=sub, step_angle_x100=ang)
            case RunPulses(motor=m, pulses=p):
                state = self._motors[m]
                state.params = replace(state.params, pulses=p)
            case DirectionAndStartFrequency(motor=m, direction=d, start_hz=f):
                state = self._motors[m]
                state.params = replace(state.params, direction=d, start_hz=f)
            case AccelAndSpeed(motor=m, accel_hz=a, speed_rpm=v):
                state = self._motors[m]
                state.params = replace(state.params, accel_hz=a, speed_rpm=v)
            case Run(motor=m):
                self._start_run(m, now)
            case RunAll():
                for m in MOTORS:
                    if self._start_run(m, now) and self.run_all_done == "none":
                        self._silent_runs.add(m)
            case Stop(motor=m):
                self._stop(m, now)
            case StopAll():
                for m in MOTORS:
                    self._stop(m, now)
            case Home(motor=m, stop_input=y):
                self._start_home(m, y, now)
            case SetLed(led=led, on=on):
                self._led_ops.append((now + self.led_delay_s, self._seq, led, on))
                self._seq += 1
            case Save():
                self._flash = {m: state.params for m, state in self._motors.items()}

    def _start_run(self, motor: int, now: float) -> bool:
        """Start ``motor``'s configured run unless it is moving; True if it started."""
        state = self._motors[motor]
        if state.moving_at(now):
            return False
        self._silent_runs.discard(motor)
        state.start(state.params.pulses, now)
        return True

    def _start_home(self, motor: int, stop_input: int, now: float) -> None:
        state = self._motors[motor]
        if state.moving_at(now):
            return
        state.start(None, now, stop_input)
        if stop_input != STOP_INPUT_NONE and stop_input in self._inputs:
            self._home_reached(state, now)

    def _stop(self, motor: int, now: float) -> None:
        state = self._motors[motor]
        if state.moving_at(now):
            state.halt(now)
        self._silent_runs.discard(motor)


def _frame(r2: int, r3: int, r4: int, r5: int) -> bytes:
    return FF_AA + bytes((r2, r3, r4, r5))


def _ack_bytes(cmd: QuadCommand) -> bytes:
    """The ack of ``cmd`` (not ``Run``): its reply shape, whose every byte is fixed."""
    (shape,) = cmd.reply_shapes()
    return bytes(min(allowed) for allowed in shape.pattern if allowed is not None)
