"""Simulated 11-byte "FF AA" project stepper controller (doc 000, docs/protocols.md part A).

Pure: time is passed in (seconds, float); nothing sleeps, reads a clock or does I/O.
State is evaluated lazily: every call that passes ``now`` (``handle``, ``poll``,
``set_input``, ``power_cycle``) first runs every internal transition due up to
``now`` in time order, so positions, outputs and the step trace are exact whenever
they are read after such a call.

Memory model: four 220-byte project images laid out exactly as the 0x3E dump (A.5),
in RAM and in simulated flash.  Programming commands write RAM fields of the project
selected by the last 0x6E (A0-03); 0x2E copies RAM to flash; 0x1E zeroes both;
``power_cycle`` reloads RAM from flash.  A cleared image keeps its project number in
``[0][0]`` and is zero elsewhere (0 steps, so starting it ends at once).

Kinematic model (simulator assumptions: doc 000 gives no timing, A0-09/A0-14):

* pulses per revolution = subdivision x 36000 / step_angle_x100 (A.3: 8 x 200 = 1600);
* a step moves ``run_distance / distance_per_rev`` revolutions;
* the pulse rate starts at ``min(start_hz, cruise)``, ramps linearly by ``accel_hz``
  every millisecond (``accel_hz`` 0 = no ramp) to the cruise rate
  ``speed_rpm / 60 x pulses per rev``, and ramps down the same way (a triangle if the
  move is too short to reach cruise); speed 0 never moves;
* a step: wait for its start input (level), switch its outputs and move (cut short,
  at once, when its stop input is or becomes active), then wait ``delay_ms``; the next
  step begins :data:`STEP_GAP_S` later (time the controller takes to load a step);
* stops are immediate whatever the stored stop mode (which is only stored).

``position`` is in motor pulses (a float, forward positive), as of the last call.

Behaviour the manual leaves open (simulator choices):

* project, global and I/O commands are always answered; motor commands only for
  this model's motor byte; frames that do not decode get no answer;
* 0x3E returns the RAM image; per-step commands for steps beyond the total are stored;
* repeat count N runs max(1, N) passes, 255 forever; the step loop count is the total
  number of passes of the loop body (A0-15); an impossible loop is ignored;
* ``EE DD`` follows every project end, whether 0x4E or IN3 started it, but by default
  never a stop by 0x5E or IN4 (A0-06; ``ee_dd_after_stop_s`` models a controller that
  sends it then too, that long after the stop); it is never sent before the 4E ack
  could be on the wire;
* 0x5E, 0x9E and 0xAE are answered ``OP 00 00 00`` as the manual prints (A0-04, A0-13);
  ``global_reply_echo="value"`` models a controller that echoes the request's value
  byte there instead, as the project commands echo theirs;
* a motion command while the motor is busy is acknowledged and ignored; 0x0D stops
  manual motion only; homing sets the position to 0 when IN5 becomes active.
"""

from __future__ import annotations

import enum
import itertools
import math
import random
from collections import deque
from dataclasses import dataclass
from typing import ClassVar, Literal

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import FF_AA, Family, check_int, wire_time
from motorbus.protocol.families import DEFAULT_BAUD
from motorbus.protocol.project_stepper import (
    BASE_DISTANCE_PER_REV,
    BASE_LOOP_START,
    BASE_MODE4,
    BASE_NUMBER,
    BASE_POWER_ON_HOMING,
    BASE_REPEAT,
    BASE_STOP_MODE,
    BASE_SUBDIVISION,
    DEFAULT_MOTOR,
    DUMP_HEADER_SIZE,
    DUMP_SIZE,
    GLOBAL_REPLY_OPCODES,
    HOME_INPUT,
    MAX_INPUT,
    MAX_PROJECT,
    OP_READ,
    OP_STEP_LOOP,
    PROJECT_FINISHED,
    PROJECT_OPCODES,
    PROJECT_START_INPUT,
    PROJECT_STOP_INPUT,
    REPEAT_FOREVER,
    REPLY_SIZE,
    STEP_ACCEL_HZ,
    STEP_COMMANDS,
    STEP_DELAY_MS,
    STEP_DIRECTION,
    STEP_DISTANCE,
    STEP_OUTPUT,
    STEP_START_INPUT,
    STEP_STOP_INPUT,
    AccelAndSpeed,
    ClearProject,
    DirectionAndStartFrequency,
    DistancePerRev,
    Home,
    JogForward,
    JogReverse,
    ManualStop,
    MotorSetup,
    OutputPort,
    ProjectDump,
    ProjectStepperCommand,
    ReadInput,
    ReadProject,
    RepeatCount,
    RotationDirection,
    RunDistance,
    SaveProject,
    SelectProject,
    SetMode4,
    SetOutput,
    SetPowerOnHoming,
    SingleRun,
    StartInput,
    StartProject,
    StepDelay,
    StepLoop,
    StepOutput,
    StepOutputCode,
    StepSpec,
    StopInput,
    StopMode,
    StopProject,
    check_motor,
    decode_request,
    dump_offset,
)
from motorbus.sim.model import DeviceModel

__all__ = [
    "ACCEL_STEP_S",
    "DEFAULT_TURNAROUND_S",
    "MAX_TRACE",
    "OUTPUT_NAMES",
    "STEP_GAP_S",
    "MoveProfile",
    "ProjectStepperModel",
    "StepTrace",
]

#: Reply turnaround.  Simulator assumption: doc 000 gives no figure (A0-14).
DEFAULT_TURNAROUND_S = 1e-3
#: ``accel_hz`` is read as "Hz per millisecond".  Simulator assumption: the slope unit
#: is unstated (A.3, A0-09).
ACCEL_STEP_S = 1e-3
#: Time between the end of one step and the start of the next.  Simulator assumption
#: (the controller must load the next step); it also keeps a loop of empty steps from
#: spinning at one instant.
STEP_GAP_S = 1e-3
#: The baud rate of doc 000 (A.1), from the family registry.
_BAUD = DEFAULT_BAUD[Family.PROJECT_STEPPER]
#: Oldest step-trace entries are dropped beyond this (a forever loop would grow it).
MAX_TRACE = 10_000
#: Output names, in the order OUT1..OUT3 (open collector) then LED1, LED2 (A.3).
OUTPUT_NAMES = ("OUT1", "OUT2", "OUT3", "LED1", "LED2")
#: Degrees x 100 in one revolution: pulses/rev = subdivision x 36000 / angle x 100 (A.3).
_CENTIDEGREES_PER_REV = 36000
_IMAGE_SIZE = DUMP_SIZE - DUMP_HEADER_SIZE


@dataclass(frozen=True, slots=True)
class StepTrace:
    """One step beginning during a project run (recorded in ``model.trace``).

    Attributes:
        time: when the step began, s (before its start-input wait).
        project: the running project, 1..4.
        step: the step number, 1..10.
    """

    time: float
    project: int
    step: int


@dataclass(frozen=True, slots=True)
class MoveProfile:
    """A trapezoidal (or triangular) pulse-rate profile; see the module docstring.

    Attributes:
        pulses: pulses to travel (``math.inf`` = continuous, for jogs and homing).
        start_rate: pulse rate at the start and end, Hz.
        peak_rate: highest pulse rate reached, Hz (0 = never moves).
        accel: ramp slope, Hz/s (0 = no ramp).
        ramp_time: duration of each ramp, s.
        cruise_time: time at ``peak_rate``, s (``math.inf`` for continuous moves).
    """

    pulses: float
    start_rate: float
    peak_rate: float
    accel: float
    ramp_time: float
    cruise_time: float

    @classmethod
    def plan(cls, pulses: float, start_hz: float, cruise_hz: float, accel_hz: float) -> MoveProfile:
        """Plan a move of ``pulses`` pulses.

        Args:
            pulses: distance, pulses (``math.inf`` = continuous).
            start_hz: start frequency, Hz (clipped to the cruise rate).
            cruise_hz: cruise pulse rate, Hz.
            accel_hz: accel setting, Hz per :data:`ACCEL_STEP_S` (0 = no ramp).

        Returns:
            The profile; a zero move lasts 0 s, a move at cruise 0 lasts forever.
        """
        if pulses <= 0:
            return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if cruise_hz <= 0:
            return cls(pulses, 0.0, 0.0, 0.0, 0.0, math.inf)
        f0 = min(float(start_hz), cruise_hz)
        accel = accel_hz / ACCEL_STEP_S
        if accel <= 0 or f0 >= cruise_hz:
            return cls(pulses, f0, cruise_hz, 0.0, 0.0, pulses / cruise_hz)
        ramp = (cruise_hz - f0) / accel
        ramp_pulses = (f0 + cruise_hz) / 2 * ramp
        if pulses >= 2 * ramp_pulses:
            return cls(pulses, f0, cruise_hz, accel, ramp, (pulses - 2 * ramp_pulses) / cruise_hz)
        peak = math.sqrt(f0 * f0 + accel * pulses)
        return cls(pulses, f0, peak, accel, (peak - f0) / accel, 0.0)

    @property
    def duration(self) -> float:
        """Total time of the move, s (``math.inf`` if it never ends)."""
        return 2 * self.ramp_time + self.cruise_time

    def pulses_at(self, t: float) -> float:
        """Return the pulses travelled ``t`` seconds after the start (clamped to the move)."""
        if t <= 0 or self.peak_rate <= 0:
            return 0.0
        if t >= self.duration:
            return self.pulses
        a, f0, tr = self.accel, self.start_rate, self.ramp_time
        if t < tr:
            return f0 * t + a * t * t / 2
        ramp_pulses = f0 * tr + a * tr * tr / 2 if tr > 0 else 0.0
        if t < tr + self.cruise_time:
            return ramp_pulses + self.peak_rate * (t - tr)
        td = t - tr - self.cruise_time
        return (
            ramp_pulses + self.peak_rate * self.cruise_time + self.peak_rate * td - a * td * td / 2
        )


@dataclass(slots=True)
class _Motion:
    """The motor's current motion: a profile started at ``start`` in direction ``sign``."""

    profile: MoveProfile
    start: float
    sign: int

    @property
    def end(self) -> float:
        return self.start + self.profile.duration

    def travelled(self, now: float) -> float:
        return self.sign * self.profile.pulses_at(now - self.start)


class _Manual(enum.Enum):
    JOG = "jog"
    SINGLE = "single"
    HOME = "home"


class _Phase(enum.Enum):
    WAIT_START = "wait_start"
    MOVE = "move"
    DELAY = "delay"


@dataclass(slots=True)
class _Run:
    """A running project: the step order of one pass and where it stands."""

    project: int
    steps: tuple[StepSpec, ...]
    pulses_per_rev: float
    distance_per_rev: int
    order: tuple[int, ...]  # step numbers of one pass, step loop unrolled (A0-15)
    passes: int | None  # total passes, None = forever (A.4 0x8E 255)
    started: float
    notify: bool  # send EE DD at the end
    pass_index: int = 0
    position: int = 0  # index into ``order``
    phase: _Phase = _Phase.WAIT_START
    phase_end: float = math.inf

    @property
    def spec(self) -> StepSpec:
        return self.steps[self.order[self.position] - 1]

    def profile(self, spec: StepSpec) -> MoveProfile:
        revs = spec.run_distance / self.distance_per_rev if self.distance_per_rev else 0.0
        cruise = spec.speed_rpm / 60 * self.pulses_per_rev
        return MoveProfile.plan(revs * self.pulses_per_rev, spec.start_hz, cruise, spec.accel_hz)


def _pulses_per_rev(subdivision: int, step_angle_x100: int) -> float:
    if step_angle_x100 <= 0:
        return 0.0
    return subdivision * _CENTIDEGREES_PER_REV / step_angle_x100


#: Byte 3 of the 0x5E/0x9E/0xAE replies: 00 as printed, or the request's value echoed.
GlobalReplyEcho = Literal["zero", "value"]


def _step_order(n: int, start: int, end: int, count: int) -> tuple[int, ...]:
    """One pass: steps 1..n with ``start..end`` repeated ``count`` times in total (A0-15).

    A disabled (0, 0, 0) or impossible loop (outside 1..n) runs every step once.
    """
    if not (1 <= start <= end <= n and count >= 1):
        return tuple(range(1, n + 1))
    body = tuple(range(start, end + 1))
    return tuple(range(1, start)) + body * count + tuple(range(end + 1, n + 1))


def _reply(b2: int, b3: int, b4: int, b5: int) -> bytes:
    return FF_AA + bytes((b2, b3, b4, b5))


def _cleared_image(project: int) -> bytes:
    image = bytearray(_IMAGE_SIZE)
    image[dump_offset(0, BASE_NUMBER) - DUMP_HEADER_SIZE] = project
    return bytes(image)


class ProjectStepperModel(DeviceModel):
    """A simulated project stepper controller (doc 000) driving one motor.

    Args:
        motor: the motor byte it answers to (default 0x03, A0-02).
        turnaround_s: reply turnaround, s (default 1 ms; the manual gives none).
        turnaround_jitter_s: extra uniform random turnaround 0..this, s.
        global_reply_echo: the 0x5E/0x9E/0xAE reply's byte 3: ``"zero"`` (the manual,
            A0-04/A0-13) or ``"value"`` (the request's byte 3 echoed, a variant).
        ee_dd_after_stop_s: ``None`` (default): no ``EE DD`` when a running project is
            stopped (0x5E or IN4); a number of seconds >= 0: send it that long after the
            stop (A0-06 leaves it open; a controller that decelerates first sends it later).

    Raises:
        LocalProtocolError: ``motor``, a time or a variant is out of range.
    """

    family: ClassVar[Family] = Family.PROJECT_STEPPER

    def __init__(
        self,
        motor: int = DEFAULT_MOTOR,
        *,
        turnaround_s: float = DEFAULT_TURNAROUND_S,
        turnaround_jitter_s: float = 0.0,
        global_reply_echo: GlobalReplyEcho = "zero",
        ee_dd_after_stop_s: float | None = None,
    ) -> None:
        self.motor = check_motor(motor)
        if global_reply_echo not in ("zero", "value"):
            raise LocalProtocolError(
                f"global_reply_echo={global_reply_echo!r} is not allowed: choose 'zero' or 'value'",
                field="global_reply_echo",
                value=global_reply_echo,
            )
        if ee_dd_after_stop_s is not None and (
            isinstance(ee_dd_after_stop_s, bool)
            or not isinstance(ee_dd_after_stop_s, int | float)
            or not 0 <= ee_dd_after_stop_s < math.inf
        ):
            raise LocalProtocolError(
                f"ee_dd_after_stop_s={ee_dd_after_stop_s!r} is out of range: allowed None "
                "or a finite number of seconds >= 0",
                field="ee_dd_after_stop_s",
                value=ee_dd_after_stop_s,
            )
        self.global_reply_echo: GlobalReplyEcho = global_reply_echo
        self.ee_dd_after_stop_s = ee_dd_after_stop_s
        for name, value in (
            ("turnaround_s", turnaround_s),
            ("turnaround_jitter_s", turnaround_jitter_s),
        ):
            if not isinstance(value, int | float) or not 0 <= value < math.inf:
                raise LocalProtocolError(
                    f"{name} must be a finite number of seconds >= 0, got {value!r}",
                    field=name,
                    value=value,
                )
        self._turnaround_s = float(turnaround_s)
        self._jitter_s = float(turnaround_jitter_s)
        self._flash: list[bytes] = [_cleared_image(p) for p in range(1, MAX_PROJECT + 1)]
        self._ram: list[bytearray] = [bytearray(image) for image in self._flash]
        self._inputs = [False] * MAX_INPUT
        #: Every step begun by a project run, oldest first (bounded by MAX_TRACE).
        self.trace: deque[StepTrace] = deque(maxlen=MAX_TRACE)
        self._reset_volatile(0.0)

    def _reset_volatile(self, now: float) -> None:
        self._now = now
        self._current_project = 1
        self._outputs = dict.fromkeys(OUTPUT_NAMES, False)
        self._position = 0.0  # pulses, at the start of ``_motion`` (or now, if idle)
        self._motion: _Motion | None = None
        self._manual: _Manual | None = None
        self._run: _Run | None = None
        self._pending: list[tuple[float, bytes]] = []
        self._finish_cache: tuple[_Run | None, float | None] | None = None

    # -- test hooks -------------------------------------------------------------------

    @property
    def current_project(self) -> int:
        """The project selected by the last 0x6E (1 after power-up), 1..4 (A0-03)."""
        return self._current_project

    @property
    def position(self) -> float:
        """Motor position in pulses (forward positive), as of the last call given ``now``."""
        if self._motion is None:
            return self._position
        return self._position + self._motion.travelled(self._now)

    @property
    def running(self) -> bool:
        """True while a project runs or a manual motion (jog, single run, homing) is on."""
        return self._run is not None or self._manual is not None

    @property
    def project_running(self) -> int | None:
        """The number of the running project, or None."""
        return self._run.project if self._run is not None else None

    @property
    def outputs(self) -> dict[str, bool]:
        """Output states, True = active: OUT1..OUT3 and LED1, LED2 (A.3)."""
        return dict(self._outputs)

    @property
    def inputs(self) -> tuple[bool, ...]:
        """Input levels IN1..IN5, True = active."""
        return tuple(self._inputs)

    def stored_image(self, project: int, *, flash: bool = False) -> bytes:
        """Return the 220 data bytes of ``project`` (RAM, or flash if ``flash``).

        Raises:
            LocalProtocolError: ``project`` is not 1..4.
        """
        check_int("project", project, 1, MAX_PROJECT)
        return bytes(self._flash[project - 1] if flash else self._ram[project - 1])

    def set_input(self, n: int, active: bool, now: float) -> None:
        """Drive input ``n`` (1..5) to ``active`` at time ``now`` (s).

        A rising IN3 starts the selected project, a rising IN4 stops the running one
        (A.3); IN5 ends homing; any input may release a start wait or stop a step.

        Raises:
            LocalProtocolError: ``n`` is not 1..5.
        """
        check_int("input", n, 1, MAX_INPUT)
        self._advance(now)
        rising = active and not self._inputs[n - 1]
        self._inputs[n - 1] = bool(active)
        self._finish_cache = None
        if rising and n == PROJECT_START_INPUT:
            self._start_project(self._current_project, now)
        if rising and n == PROJECT_STOP_INPUT:
            self._stop_project(now)
        run = self._run
        if run is not None and active:
            if run.phase is _Phase.WAIT_START and run.spec.start_input == n:
                self._begin_move(run, now)
            elif run.phase is _Phase.MOVE and run.spec.stop_input == n:
                self._end_motion(now)
                self._begin_delay(run, now)
        if self._manual is _Manual.HOME and active and n == HOME_INPUT:
            self._finish_homing(now)
        self._advance(now)

    # -- DeviceModel ------------------------------------------------------------------

    def handle(self, request: bytes, now: float) -> list[bytes]:
        """Answer one request at ``now`` (s); a frame for another motor or a bad one gets []."""
        self._advance(now)
        try:
            cmd = decode_request(request)
        except RemoteProtocolError:
            return []  # a real controller ignores a frame it cannot parse
        motor = getattr(cmd, "motor", None)
        if motor is not None and motor != self.motor:
            return []
        self._finish_cache = None
        reply = self._dispatch(cmd, now)
        self._advance(now)
        return [reply]

    def poll(self, now: float) -> list[bytes]:
        """Advance to ``now`` (s); return ``EE DD`` if a project finished by then."""
        self._advance(now)
        due = [frame for t, frame in self._pending if t <= now]
        self._pending = [(t, f) for t, f in self._pending if t > now]
        return due

    def next_event_time(self) -> float | None:
        """When the next ``EE DD`` is due, or None (idle, waiting for an input, forever)."""
        times = [t for t, _ in self._pending]
        finish = self._predicted_finish()
        if finish is not None:
            times.append(finish)
        return min(times) if times else None

    def turnaround(self, rng: random.Random) -> float:
        """Seconds from the end of a request to the first reply byte."""
        if self._jitter_s <= 0:
            return self._turnaround_s
        return self._turnaround_s + rng.uniform(0.0, self._jitter_s)

    def power_cycle(self, now: float) -> None:
        """Power off and on at ``now`` (s): motion stops, RAM reloads from flash.

        Inputs are external and keep their levels; if the (new) current project 1 has
        power-on homing enabled, homing starts at once (A.4 0xAE).
        """
        self._advance(now)
        self._ram = [bytearray(image) for image in self._flash]
        self._reset_volatile(now)
        if self._base(self._current_project, BASE_POWER_ON_HOMING):
            self._start_manual(_Manual.HOME, now)

    # -- commands ---------------------------------------------------------------------

    def _dispatch(self, cmd: ProjectStepperCommand[object], now: float) -> bytes:
        cur = self._current_project
        payload = cmd.body()
        match cmd:
            case SelectProject(project=p, total_steps=n):
                self._current_project = p
                self._put(p, 0, BASE_NUMBER, bytes((p, n)))
            case StepLoop(start=s, end=e, count=c):
                self._put(cur, 0, BASE_LOOP_START, bytes((s, e, c)))
                return _reply(OP_STEP_LOOP, cur, 0, 0)  # echoes the current project (A0-03)
            case RepeatCount(count=c):
                self._put(cur, 0, BASE_REPEAT, bytes((c,)))
                return _reply(payload[0], cur, 0, 0)
            case StartProject(project=p):
                self._start_project(p, now)
            case StopProject():
                self._stop_project(now)
            case ReadProject(project=p):
                return FF_AA + bytes((OP_READ, p, 0, 0)) + bytes(self._ram[p - 1])
            case SaveProject(project=p):
                self._flash[p - 1] = bytes(self._ram[p - 1])
            case ClearProject(project=p):
                self._flash[p - 1] = _cleared_image(p)
                self._ram[p - 1] = bytearray(self._flash[p - 1])
            case SetMode4(value=v):
                self._put(cur, 0, BASE_MODE4, bytes((v,)))
            case SetPowerOnHoming(enabled=on):
                self._put(cur, 0, BASE_POWER_ON_HOMING, bytes((int(on),)))
            case MotorSetup(subdivision=sub, step_angle_x100=angle):
                self._put(cur, 0, BASE_SUBDIVISION, sub.to_bytes(2, "little") + bytes((angle,)))
            case DistancePerRev(value=v):
                self._put(cur, 0, BASE_DISTANCE_PER_REV, v.to_bytes(3, "little"))
            case RunDistance(step=s, distance=d):
                self._put(cur, s, STEP_DISTANCE, d.to_bytes(3, "little"))
            case DirectionAndStartFrequency(step=s, direction=d, start_hz=f):
                self._put(cur, s, STEP_DIRECTION, bytes((d,)) + f.to_bytes(2, "little"))
            case AccelAndSpeed(step=s, accel_hz=a, speed_rpm=v):
                self._put(cur, s, STEP_ACCEL_HZ, a.to_bytes(2, "little") + v.to_bytes(2, "little"))
            case StepOutput(step=s, code=c):
                self._put(cur, s, STEP_OUTPUT, bytes((c,)))
            case StepDelay(step=s, delay_ms=t):
                self._put(cur, s, STEP_DELAY_MS, t.to_bytes(3, "little"))
            case StartInput(step=s, input_number=n):
                self._put(cur, s, STEP_START_INPUT, bytes((n,)))
            case StopInput(step=s, input_number=n):
                self._put(cur, s, STEP_STOP_INPUT, bytes((n,)))
            case JogForward() | JogReverse() | SingleRun() | Home():
                kind = {
                    JogForward: _Manual.JOG,
                    JogReverse: _Manual.JOG,
                    SingleRun: _Manual.SINGLE,
                    Home: _Manual.HOME,
                }[type(cmd)]
                self._start_manual(kind, now, reverse=isinstance(cmd, JogReverse))
            case ManualStop():
                if self._manual is not None:
                    self._end_motion(now)
                    self._manual = None
            case StopMode(mode=m):
                self._put(cur, 0, BASE_STOP_MODE, bytes((m,)))
            case SetOutput(port=port, level=level):
                self._set_port(port, bool(level))
                return _reply(payload[0], payload[1], port, 0)
            case ReadInput(input_number=n):
                return _reply(payload[0], payload[1], n, int(self._inputs[n - 1]))
        # A.7: project commands echo P, 5E/9E/AE echo nothing, motor commands M CMD 00 S.
        op = payload[0]
        if op in GLOBAL_REPLY_OPCODES:
            return _reply(op, payload[1] if self.global_reply_echo == "value" else 0, 0, 0)
        if op in PROJECT_OPCODES:
            return _reply(op, payload[1], 0, 0)
        return _reply(op, payload[1], 0, payload[7] if payload[1] in STEP_COMMANDS else 0)

    def _put(self, project: int, block: int, k: int, data: bytes) -> None:
        off = dump_offset(block, k) - DUMP_HEADER_SIZE
        self._ram[project - 1][off : off + len(data)] = data

    def _base(self, project: int, k: int) -> int:
        return self._ram[project - 1][dump_offset(0, k) - DUMP_HEADER_SIZE]

    def _dump(self, project: int) -> ProjectDump:
        header = FF_AA + bytes((OP_READ, project, 0, 0))
        return ProjectDump.decode(header + bytes(self._ram[project - 1]))

    def _set_port(self, port: int, active: bool) -> None:
        if port == OutputPort.ALL_OUTPUTS:
            names: tuple[str, ...] = OUTPUT_NAMES[:3]
        elif port == OutputPort.LEDS:
            names = OUTPUT_NAMES[3:]
        else:
            names = (OUTPUT_NAMES[port - 1],)
        for name in names:
            self._outputs[name] = active

    def _apply_step_output(self, code: StepOutputCode) -> None:
        if code == StepOutputCode.NONE:
            return
        if code == StepOutputCode.ALL_ON:
            self._set_port(OutputPort.ALL_OUTPUTS, True)
        elif code == StepOutputCode.ALL_OFF:
            self._set_port(OutputPort.ALL_OUTPUTS, False)
        elif code <= StepOutputCode.OUT3_ON:
            self._set_port(code, True)
        else:
            self._set_port(code - StepOutputCode.OUT1_OFF + 1, False)

    # -- motion -----------------------------------------------------------------------

    def _end_motion(self, now: float) -> None:
        if self._motion is not None:
            self._position += self._motion.travelled(now)
            self._motion = None

    def _start_manual(self, kind: _Manual, now: float, *, reverse: bool = False) -> None:
        """Jog, single run or homing with project 1 step 1 parameters (A0-12)."""
        if self.running:
            return  # the controller is busy: acknowledged, ignored (simulator choice)
        try:
            dump = self._dump(1)
            spec = dump.steps[0] if dump.steps else StepSpec(run_distance=0, speed_rpm=0)
        except (RemoteProtocolError, LocalProtocolError):
            return
        ppr = _pulses_per_rev(dump.subdivision, dump.step_angle_x100)
        cruise = spec.speed_rpm / 60 * ppr
        if kind is _Manual.HOME:
            if self._inputs[HOME_INPUT - 1]:
                self._position = 0.0  # already at the sensor
                return
            pulses, sign = math.inf, -1
        elif kind is _Manual.JOG:
            pulses, sign = math.inf, -1 if reverse else 1
        else:
            dpr = dump.distance_per_rev
            pulses = spec.run_distance / dpr * ppr if dpr else 0.0
            sign = -1 if spec.direction == RotationDirection.REVERSE else 1
        profile = MoveProfile.plan(pulses, spec.start_hz, cruise, spec.accel_hz)
        self._motion = _Motion(profile, now, sign)
        self._manual = kind

    def _finish_homing(self, now: float) -> None:
        self._end_motion(now)
        self._manual = None
        self._position = 0.0  # the sensor defines zero

    # -- project runs -----------------------------------------------------------------

    def _start_project(self, project: int, now: float) -> None:
        if self.running:
            return  # busy: acknowledged, ignored (simulator choice)
        try:
            dump = self._dump(project)
        except RemoteProtocolError:
            return
        n = len(dump.steps)
        run = _Run(
            project=project,
            steps=dump.steps,
            pulses_per_rev=_pulses_per_rev(dump.subdivision, dump.step_angle_x100),
            distance_per_rev=dump.distance_per_rev,
            order=_step_order(n, dump.loop_start, dump.loop_end, dump.loop_count),
            passes=None if dump.repeat_count == REPEAT_FOREVER else max(1, dump.repeat_count),
            started=now,
            notify=True,
        )
        self._run = run
        if not run.order:
            self._finish_project(now)
            return
        self._enter_step(run, now)

    def _enter_step(self, run: _Run, t: float) -> None:
        self.trace.append(StepTrace(t, run.project, run.order[run.position]))
        run.phase = _Phase.WAIT_START
        run.phase_end = math.inf
        gate = run.spec.start_input
        if gate == 0 or self._inputs[gate - 1]:
            self._begin_move(run, t)

    def _begin_move(self, run: _Run, t: float) -> None:
        spec = run.spec
        self._apply_step_output(spec.output)  # outputs switch with the motion (A.4 06)
        stop = spec.stop_input
        if stop and self._inputs[stop - 1]:
            self._begin_delay(run, t)  # the stop input holds the motor
            return
        sign = -1 if spec.direction == RotationDirection.REVERSE else 1
        self._motion = _Motion(run.profile(spec), t, sign)
        run.phase = _Phase.MOVE
        run.phase_end = self._motion.end

    def _begin_delay(self, run: _Run, t: float) -> None:
        run.phase = _Phase.DELAY
        run.phase_end = t + run.spec.delay_ms / 1000

    def _next_step(self, run: _Run, t: float) -> None:
        run.position += 1
        if run.position >= len(run.order):
            run.pass_index += 1
            run.position = 0
            if run.passes is not None and run.pass_index >= run.passes:
                self._finish_project(t)
                return
        self._enter_step(run, t + STEP_GAP_S)

    def _finish_project(self, t: float) -> None:
        run = self._run
        self._run = None
        if run is not None and run.notify:
            self._pending.append((max(t, self._earliest_finish(run)), PROJECT_FINISHED))

    def _earliest_finish(self, run: _Run) -> float:
        # Keep EE DD behind the 4E acknowledgement on the wire.
        return run.started + self._turnaround_s + wire_time(REPLY_SIZE, _BAUD)

    def _stop_project(self, now: float) -> None:
        """0x5E / IN4: stop at once, no EE DD (A.4) unless ``ee_dd_after_stop_s``."""
        run = self._run
        if run is not None:
            self._end_motion(now)
            delay = self.ee_dd_after_stop_s
            if delay is not None and run.notify:
                due = max(now + delay, self._earliest_finish(run))
                self._pending.append((due, PROJECT_FINISHED))
            self._run = None

    # -- time -------------------------------------------------------------------------

    def _next_transition(self) -> float | None:
        run = self._run
        if run is not None and run.phase is not _Phase.WAIT_START:
            if run.phase is _Phase.DELAY:
                return run.phase_end
            return run.phase_end if run.phase_end < math.inf else None
        if self._manual is _Manual.SINGLE and self._motion is not None:
            return self._motion.end
        return None

    def _advance(self, now: float) -> None:
        """Run every transition due at or before ``now``, in time order."""
        while True:
            t = self._next_transition()
            if t is None or t > now:
                break
            run = self._run
            if run is not None and run.phase is _Phase.MOVE:
                self._end_motion(t)
                self._begin_delay(run, t)
            elif run is not None and run.phase is _Phase.DELAY:
                self._next_step(run, t)
            else:  # a single run reached its distance
                self._end_motion(t)
                self._manual = None
        self._now = max(self._now, now)

    def _predicted_finish(self) -> float | None:
        """When the running project will end if no input changes; None if unknowable.

        Cached per run until a request or an input change: the run itself evolves
        deterministically, and the prediction repeats the exact float arithmetic of
        the transitions, so ``poll`` at the predicted time finds the project ended.
        """
        cache = self._finish_cache
        if cache is not None and cache[0] is self._run:
            return cache[1]
        value = self._compute_finish()
        self._finish_cache = (self._run, value)
        return value

    def _compute_finish(self) -> float | None:
        run = self._run
        if run is None or not run.notify or run.passes is None:
            return None
        if run.phase is _Phase.WAIT_START:
            return None
        t = run.phase_end
        if run.phase is _Phase.MOVE:
            t = t + run.spec.delay_ms / 1000
        more_passes = run.passes - run.pass_index - 1
        rest = itertools.chain(
            run.order[run.position + 1 :], itertools.chain.from_iterable([run.order] * more_passes)
        )
        moves: dict[int, float | None] = {}
        for step in rest:
            if step not in moves:
                moves[step] = self._move_time(run, step)
            move = moves[step]
            if move is None:
                return None  # a step still to come waits for an input that is not active
            t = t + STEP_GAP_S  # same operations, same order as the transitions
            if move:
                t = t + move
            t = t + run.steps[step - 1].delay_ms / 1000
        if not t < math.inf:
            return None
        return max(t, self._earliest_finish(run))

    def _move_time(self, run: _Run, step: int) -> float | None:
        """Duration of the move of ``step`` with today's input levels; None if it waits."""
        spec = run.steps[step - 1]
        gate, stop = spec.start_input, spec.stop_input
        if gate and not self._inputs[gate - 1]:
            return None
        if stop and self._inputs[stop - 1]:
            return 0.0
        return run.profile(spec).duration
