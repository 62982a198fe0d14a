"""Simulated 11-byte "FF AA" project stepper controller (doc 000, docs/protocols.md part A).

Pure: time is passed in (seconds, float); nothing sleeps, reads a clock or does I/O.
State is evaluated lazily: every call that passes ``now`` (``handle``, ``poll``,
``set_input``, ``power_cycle``) first runs every internal transition due up to
``now`` in time order, so positions, outputs and the step trace are exact whenever
they are read after such a call.

Memory model: four 220-byte project images laid out exactly as the 0x3E dump (A.5),
in RAM and in simulated flash.  Programming commands write RAM fields of the project
selected by the last 0x6E (A0-03); 0x2E copies RAM to flash; 0x1E zeroes both;
``power_cycle`` reloads RAM from flash.

Kinematic model (move profiles, how a project run proceeds step by step):
``motorbus.sim.project_stepper_motion``.  RAM and flash images:
``motorbus.sim.project_stepper_memory``.  This module is the device: how each request,
input change and power cycle acts on them, and when ``EE DD`` is sent.

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
    GLOBAL_REPLY_OPCODES,
    HOME_INPUT,
    MAX_INPUT,
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
)
from motorbus.sim.model import DeviceModel
from motorbus.sim.project_stepper_memory import ProjectMemory
from motorbus.sim.project_stepper_motion import (
    ACCEL_STEP_S,
    STEP_GAP_S,
    Motion,
    MoveProfile,
    Phase,
    Run,
    pulses_per_rev,
    step_order,
)

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
#: The baud rate of doc 000 (A.1), from the family registry.
_BAUD = DEFAULT_BAUD[Family.PROJECT_STEPPER]
#: Oldest step-trace entries are dropped beyond this (a forever loop would grow it).
MAX_TRACE = 10_000
#: Output names, in the order OUT1..OUT3 (open collector) then LED1, LED2 (A.3).
OUTPUT_NAMES = ("OUT1", "OUT2", "OUT3", "LED1", "LED2")


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


class _Manual(enum.Enum):
    JOG = "jog"
    SINGLE = "single"
    HOME = "home"


#: Byte 3 of the 0x5E/0x9E/0xAE replies: 00 as printed, or the request's value echoed.
GlobalReplyEcho = Literal["zero", "value"]


def _reply(b2: int, b3: int, b4: int, b5: int) -> bytes:
    return FF_AA + bytes((b2, b3, b4, b5))


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
        #: The four project images, in RAM and in flash.
        self._memory = ProjectMemory()
        self._inputs = [False] * MAX_INPUT
        #: Every step begun by a project run, oldest first (bounded by MAX_TRACE).
        self.trace: deque[StepTrace] = deque(maxlen=MAX_TRACE)
        self._reset_volatile(0.0)

    def _reset_volatile(self, now: float) -> None:
        self._now = now
        self._current_project = 1
        self._outputs = dict.fromkeys(OUTPUT_NAMES, False)
        self._position = 0.0  # pulses, at the start of ``_motion`` (or now, if idle)
        self._motion: Motion | None = None
        self._manual: _Manual | None = None
        self._run: Run | None = None
        self._pending: list[tuple[float, bytes]] = []
        self._finish_cache: tuple[Run | None, float | None] | None = None

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
        return self._memory.image(project, flash=flash)

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
            if run.phase is Phase.WAIT_START and run.spec.start_input == n:
                self._begin_move(run, now)
            elif run.phase is Phase.MOVE and run.spec.stop_input == n:
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
        self._memory.reload()
        self._reset_volatile(now)
        if self._memory.base(self._current_project, BASE_POWER_ON_HOMING):
            self._start_manual(_Manual.HOME, now)

    # -- commands ---------------------------------------------------------------------

    def _dispatch(self, cmd: ProjectStepperCommand[object], now: float) -> bytes:
        cur = self._current_project
        payload = cmd.body()
        match cmd:
            case SelectProject(project=p, total_steps=n):
                self._current_project = p
                self._memory.put(p, 0, BASE_NUMBER, bytes((p, n)))
            case StepLoop(start=s, end=e, count=c):
                self._memory.put(cur, 0, BASE_LOOP_START, bytes((s, e, c)))
                return _reply(OP_STEP_LOOP, cur, 0, 0)  # echoes the current project (A0-03)
            case RepeatCount(count=c):
                self._memory.put(cur, 0, BASE_REPEAT, bytes((c,)))
                return _reply(payload[0], cur, 0, 0)
            case StartProject(project=p):
                self._start_project(p, now)
            case StopProject():
                self._stop_project(now)
            case ReadProject(project=p):
                return self._memory.dump_bytes(p)
            case SaveProject(project=p):
                self._memory.save(p)
            case ClearProject(project=p):
                self._memory.clear(p)
            case SetMode4(value=v):
                self._memory.put(cur, 0, BASE_MODE4, bytes((v,)))
            case SetPowerOnHoming(enabled=on):
                self._memory.put(cur, 0, BASE_POWER_ON_HOMING, bytes((int(on),)))
            case MotorSetup(subdivision=sub, step_angle_x100=angle):
                self._memory.put(
                    cur, 0, BASE_SUBDIVISION, sub.to_bytes(2, "little") + bytes((angle,))
                )
            case DistancePerRev(value=v):
                self._memory.put(cur, 0, BASE_DISTANCE_PER_REV, v.to_bytes(3, "little"))
            case RunDistance(step=s, distance=d):
                self._memory.put(cur, s, STEP_DISTANCE, d.to_bytes(3, "little"))
            case DirectionAndStartFrequency(step=s, direction=d, start_hz=f):
                self._memory.put(cur, s, STEP_DIRECTION, bytes((d,)) + f.to_bytes(2, "little"))
            case AccelAndSpeed(step=s, accel_hz=a, speed_rpm=v):
                self._memory.put(
                    cur, s, STEP_ACCEL_HZ, a.to_bytes(2, "little") + v.to_bytes(2, "little")
                )
            case StepOutput(step=s, code=c):
                self._memory.put(cur, s, STEP_OUTPUT, bytes((c,)))
            case StepDelay(step=s, delay_ms=t):
                self._memory.put(cur, s, STEP_DELAY_MS, t.to_bytes(3, "little"))
            case StartInput(step=s, input_number=n):
                self._memory.put(cur, s, STEP_START_INPUT, bytes((n,)))
            case StopInput(step=s, input_number=n):
                self._memory.put(cur, s, STEP_STOP_INPUT, bytes((n,)))
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
                self._memory.put(cur, 0, BASE_STOP_MODE, bytes((m,)))
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
            dump = self._memory.dump(1)
            spec = dump.steps[0] if dump.steps else StepSpec(run_distance=0, speed_rpm=0)
        except (RemoteProtocolError, LocalProtocolError):
            return
        ppr = pulses_per_rev(dump.subdivision, dump.step_angle_x100)
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
        self._motion = Motion(profile, now, sign)
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
            dump = self._memory.dump(project)
        except RemoteProtocolError:
            return
        n = len(dump.steps)
        run = Run(
            project=project,
            steps=dump.steps,
            pulses_per_rev=pulses_per_rev(dump.subdivision, dump.step_angle_x100),
            distance_per_rev=dump.distance_per_rev,
            order=step_order(n, dump.loop_start, dump.loop_end, dump.loop_count),
            passes=None if dump.repeat_count == REPEAT_FOREVER else max(1, dump.repeat_count),
            started=now,
            notify=True,
        )
        self._run = run
        if not run.order:
            self._finish_project(now)
            return
        self._enter_step(run, now)

    def _enter_step(self, run: Run, t: float) -> None:
        self.trace.append(StepTrace(t, run.project, run.order[run.position]))
        run.phase = Phase.WAIT_START
        run.phase_end = math.inf
        gate = run.spec.start_input
        if gate == 0 or self._inputs[gate - 1]:
            self._begin_move(run, t)

    def _begin_move(self, run: Run, t: float) -> None:
        spec = run.spec
        self._apply_step_output(spec.output)  # outputs switch with the motion (A.4 06)
        stop = spec.stop_input
        if stop and self._inputs[stop - 1]:
            self._begin_delay(run, t)  # the stop input holds the motor
            return
        sign = -1 if spec.direction == RotationDirection.REVERSE else 1
        self._motion = Motion(run.profile(spec), t, sign)
        run.phase = Phase.MOVE
        run.phase_end = self._motion.end

    def _begin_delay(self, run: Run, t: float) -> None:
        run.phase = Phase.DELAY
        run.phase_end = t + run.spec.delay_ms / 1000

    def _next_step(self, run: Run, t: float) -> None:
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

    def _earliest_finish(self, run: Run) -> float:
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
        if run is not None and run.phase is not Phase.WAIT_START:
            if run.phase is Phase.DELAY:
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
            if run is not None and run.phase is Phase.MOVE:
                self._end_motion(t)
                self._begin_delay(run, t)
            elif run is not None and run.phase is Phase.DELAY:
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
        if run is None or not run.notify:
            return None
        t = run.finish_time(self._inputs)
        if t is None:
            return None
        return max(t, self._earliest_finish(run))
