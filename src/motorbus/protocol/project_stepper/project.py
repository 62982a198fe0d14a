"""Projects as values: ``StepSpec``, ``Project``, ``ProjectDump`` and the 226-byte dump
codec (doc 000 A.3, A.5)."""

from __future__ import annotations

from dataclasses import dataclass, field

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import FF_AA, check_choice, check_int, format_hex
from motorbus.protocol.ff_aa import RotationDirection
from motorbus.protocol.project_stepper.wire import (
    _ANY_PROJECT,
    DUMP_BLOCK_SIZE,
    DUMP_SIZE,
    MAX_LOOP_COUNT,
    MAX_PROJECT,
    MAX_STEP_ANGLE_X100,
    MAX_STEPS,
    MAX_U16,
    MAX_U24,
    MODE4_VALUES,
    OP_READ,
    REPEAT_FOREVER,
    GatingInput,
    StepOutputCode,
    StopBehavior,
    _check_project,
    _le,
    _u16,
    _u24,
    dump_offset,
)

# -- project values ------------------------------------------------------------------------


#: Offsets inside the base block [0][k] of the dump (A.5).
BASE_NUMBER = 0
BASE_STEPS = 1
BASE_LOOP_START = 2
BASE_LOOP_END = 3
BASE_LOOP_COUNT = 4
BASE_REPEAT = 5
BASE_SUBDIVISION = 6  # 2 bytes
BASE_STEP_ANGLE = 8
BASE_DISTANCE_PER_REV = 9  # 3 bytes
BASE_STOP_MODE = 14
BASE_MODE4 = 15
BASE_POWER_ON_HOMING = 16
#: Base-block bytes the manual does not list (A.5, A0-07).
BASE_RESERVED = (12, 13, 17, 18, 19)

#: Offsets inside a step block [x][k] of the dump (A.5).
STEP_DISTANCE = 0  # 3 bytes
STEP_DIRECTION = 3
STEP_START_HZ = 4  # 2 bytes
STEP_ACCEL_HZ = 6  # 2 bytes
STEP_SPEED_RPM = 8  # 2 bytes
STEP_OUTPUT = 10
STEP_DELAY_MS = 11  # 3 bytes
STEP_START_INPUT = 14
STEP_STOP_INPUT = 15
#: Step-block bytes the manual does not list (A.5, A0-07).
STEP_RESERVED = (16, 17, 18, 19)
#: Data bytes of a step block (all but the reserved tail).
STEP_DATA_SIZE = 16

#: Every reserved byte of the 220-byte dump data, in offset order (5 base + 4 per step).
RESERVED_SIZE = len(BASE_RESERVED) + MAX_STEPS * len(STEP_RESERVED)


@dataclass(frozen=True, slots=True, kw_only=True)
class StepSpec:
    """The parameters of one step (A.4 cmds 03..09).

    Attributes:
        run_distance: user units (revolutions = distance / distance per rev), 24-bit.
        direction: FORWARD or REVERSE.
        start_hz: start frequency, Hz, 0..65535.
        accel_hz: accel/decel frequency, Hz, 0..65535 (the slope unit is unstated, A0-09).
        speed_rpm: run speed, RPM, 0..65535.
        output: output action switched with the motion (A0-10).
        delay_ms: delay after the motion, ms, 24-bit.
        start_input: input that must be active before the step runs (0 = none).
        stop_input: input that stops the motor during the step (0 = none).
    """

    run_distance: int
    direction: RotationDirection = RotationDirection.FORWARD
    start_hz: int = 0
    accel_hz: int = 0
    speed_rpm: int
    output: StepOutputCode = StepOutputCode.NONE
    delay_ms: int = 0
    start_input: GatingInput = GatingInput.NONE
    stop_input: GatingInput = GatingInput.NONE

    def __post_init__(self) -> None:
        check_int("run_distance", self.run_distance, 0, MAX_U24)
        d = check_choice("direction", self.direction, tuple(RotationDirection), "0 fwd, 1 rev")
        object.__setattr__(self, "direction", RotationDirection(d))
        check_int("start_hz", self.start_hz, 0, MAX_U16)
        check_int("accel_hz", self.accel_hz, 0, MAX_U16)
        check_int("speed_rpm", self.speed_rpm, 0, MAX_U16)
        o = check_choice("output", self.output, tuple(StepOutputCode), "A0-10")
        object.__setattr__(self, "output", StepOutputCode(o))
        check_int("delay_ms", self.delay_ms, 0, MAX_U24)
        s = check_choice("start_input", self.start_input, tuple(GatingInput), "A0-11")
        object.__setattr__(self, "start_input", GatingInput(s))
        t = check_choice("stop_input", self.stop_input, tuple(GatingInput), "A0-11")
        object.__setattr__(self, "stop_input", GatingInput(t))

    def encode_data(self) -> bytes:
        """Return the 16 data bytes of this step's dump block (``[x][0..15]``, A.5)."""
        return (
            _u24(self.run_distance)
            + bytes((self.direction,))
            + _u16(self.start_hz)
            + _u16(self.accel_hz)
            + _u16(self.speed_rpm)
            + bytes((self.output,))
            + _u24(self.delay_ms)
            + bytes((self.start_input, self.stop_input))
        )

    @classmethod
    def decode_data(cls, data: bytes) -> StepSpec:
        """Decode the 16 data bytes of a dump step block (``[x][0..15]``, A.5).

        Raises:
            LocalProtocolError: ``data`` is not 16 bytes or holds an out-of-range code.
        """
        if len(data) != STEP_DATA_SIZE:
            raise LocalProtocolError(
                f"step data must be {STEP_DATA_SIZE} bytes, got {len(data)}",
                field="data",
                value=bytes(data),
            )
        return cls(
            run_distance=_le(data[STEP_DISTANCE : STEP_DISTANCE + 3]),
            direction=data[STEP_DIRECTION],  # type: ignore[arg-type]  # validated on init
            start_hz=_le(data[STEP_START_HZ : STEP_START_HZ + 2]),
            accel_hz=_le(data[STEP_ACCEL_HZ : STEP_ACCEL_HZ + 2]),
            speed_rpm=_le(data[STEP_SPEED_RPM : STEP_SPEED_RPM + 2]),
            output=data[STEP_OUTPUT],  # type: ignore[arg-type]  # validated on init
            delay_ms=_le(data[STEP_DELAY_MS : STEP_DELAY_MS + 3]),
            start_input=data[STEP_START_INPUT],  # type: ignore[arg-type]
            stop_input=data[STEP_STOP_INPUT],  # type: ignore[arg-type]
        )


@dataclass(frozen=True, slots=True)
class Project:
    """A complete project: motor configuration, 1..10 steps, step loop and repeat count.

    Attributes:
        number: project number 1..4 (the ``project`` of the commands, acks and
            :class:`ProjectDump`; ``number`` in a project TOML file).
        subdivision: microstep subdivision, 1..65535.
        step_angle_x100: motor step angle, degrees x 100, 1..255 (A0-09).
        distance_per_rev: user units per revolution, 1..16777215 (A.3).
        steps: 1..10 steps.
        loop_start, loop_end, loop_count: step loop; (0, 0, 0) = none, otherwise
            ``1 <= loop_start <= loop_end <= len(steps)`` and count 1..254, total passes (A0-15).
        repeat_count: project repeat count 0..254, 255 = forever (A.4 0x8E).
    """

    number: int
    subdivision: int
    step_angle_x100: int
    distance_per_rev: int
    steps: tuple[StepSpec, ...]
    loop_start: int = 0
    loop_end: int = 0
    loop_count: int = 0
    repeat_count: int = 0

    def __post_init__(self) -> None:
        check_int("number", self.number, 1, MAX_PROJECT)
        check_int("subdivision", self.subdivision, 1, MAX_U16)
        check_int("step_angle_x100", self.step_angle_x100, 1, MAX_STEP_ANGLE_X100)
        check_int("distance_per_rev", self.distance_per_rev, 1, MAX_U24)
        if not isinstance(self.steps, tuple) or not all(
            isinstance(s, StepSpec) for s in self.steps
        ):
            raise LocalProtocolError(
                f"steps must be a tuple of StepSpec, got {self.steps!r}",
                field="steps",
                value=self.steps,
            )
        check_int("len(steps)", len(self.steps), 1, MAX_STEPS)
        if (self.loop_start, self.loop_end, self.loop_count) != (0, 0, 0):
            check_int("loop_start", self.loop_start, 1, len(self.steps))
            check_int("loop_end", self.loop_end, self.loop_start, len(self.steps))
            check_int("loop_count", self.loop_count, 1, MAX_LOOP_COUNT)
        check_int("repeat_count", self.repeat_count, 0, REPEAT_FOREVER)


def _zero_unused(used: int) -> bytes:
    return bytes(STEP_DATA_SIZE * (MAX_STEPS - used))


@dataclass(frozen=True, slots=True)
class ProjectDump:
    """The 226-byte reply to 0x3E, decoded (A.5, A0-07).

    Base-block fields are the raw stored integers (a cleared project reads zeros).
    ``steps`` holds the used step blocks (the first ``number_of_steps``, at most 10);
    the data bytes of the unused blocks are kept raw in ``unused_steps`` and every
    unlisted byte in ``reserved``, so ``decode(encode())`` is byte-exact.

    Attributes:
        project: the project number 1..4: P of the header ``FF AA 3E P 00 00``, the
            project that was read (``Project.number`` of the project it holds).
        stored_number: ``[0][0]``, the number byte stored with the project: equal to
            ``project`` once a project is uploaded (the manual does not say what a
            cleared project holds here; the simulator keeps the number).
        number_of_steps: ``[0][1]``.
        loop_start, loop_end, loop_count: ``[0][2..4]``.
        repeat_count: ``[0][5]`` (255 = forever).
        subdivision: ``[0][6..7]``; step_angle_x100: ``[0][8]``; distance_per_rev: ``[0][9..11]``.
        stop_mode: ``[0][14]``; mode4: ``[0][15]``; power_on_homing: ``[0][16]`` (raw bytes).
        steps: decoded step blocks 1..min(number_of_steps, 10).
        unused_steps: 16 data bytes for each later block, in order.
        reserved: the 45 unlisted bytes, in offset order (``[0][12,13,17..19]``, then
            ``[x][16..19]`` for x = 1..10).
    """

    project: int
    stored_number: int
    number_of_steps: int
    loop_start: int
    loop_end: int
    loop_count: int
    repeat_count: int
    subdivision: int
    step_angle_x100: int
    distance_per_rev: int
    stop_mode: int
    mode4: int
    power_on_homing: int
    steps: tuple[StepSpec, ...]
    unused_steps: bytes = field(default=b"", repr=False)
    reserved: bytes = field(default=bytes(RESERVED_SIZE), repr=False)

    def __post_init__(self) -> None:
        _check_project(self.project)
        for name in (
            "stored_number",
            "number_of_steps",
            "loop_start",
            "loop_end",
            "loop_count",
            "repeat_count",
            "step_angle_x100",
            "stop_mode",
            "mode4",
            "power_on_homing",
        ):
            check_int(name, getattr(self, name), 0, 0xFF)
        check_int("subdivision", self.subdivision, 0, MAX_U16)
        check_int("distance_per_rev", self.distance_per_rev, 0, MAX_U24)
        used = min(self.number_of_steps, MAX_STEPS)
        check_int("len(steps)", len(self.steps), used, used)
        check_int(
            "len(unused_steps)",
            len(self.unused_steps),
            len(_zero_unused(used)),
            len(_zero_unused(used)),
        )
        check_int("len(reserved)", len(self.reserved), RESERVED_SIZE, RESERVED_SIZE)

    @classmethod
    def decode(cls, raw: bytes) -> ProjectDump:
        """Decode a 226-byte 0x3E reply.

        Raises:
            RemoteProtocolError: wrong length, wrong header, or a used step block holds
                an out-of-range code (direction, output, input).
        """
        raw = bytes(raw)
        if len(raw) != DUMP_SIZE:
            raise RemoteProtocolError(f"a dump is {DUMP_SIZE} bytes, got {len(raw)}", raw=raw)
        if raw[:3] != FF_AA + bytes((OP_READ,)) or raw[4:6] != b"\x00\x00":
            raise RemoteProtocolError(
                f"dump header {format_hex(raw[:6])} is not FF AA 3E P 00 00", raw=raw
            )
        if raw[3] not in _ANY_PROJECT:
            raise RemoteProtocolError(f"dump header names project {raw[3]}, not 1..4", raw=raw)

        def base(k: int, n: int = 1) -> int:
            off = dump_offset(0, k)
            return _le(raw[off : off + n])

        reserved = bytes(raw[dump_offset(0, k)] for k in BASE_RESERVED)
        steps: list[StepSpec] = []
        unused = b""
        used = min(base(BASE_STEPS), MAX_STEPS)
        for x in range(1, MAX_STEPS + 1):
            start = dump_offset(x, 0)
            data = raw[start : start + STEP_DATA_SIZE]
            reserved += raw[start + STEP_DATA_SIZE : start + DUMP_BLOCK_SIZE]
            if x > used:
                unused += data
                continue
            try:
                steps.append(StepSpec.decode_data(data))
            except LocalProtocolError as err:
                raise RemoteProtocolError(
                    f"dump step {x} (offset {start}): {err}", raw=raw
                ) from err
        return cls(
            project=raw[3],
            stored_number=base(BASE_NUMBER),
            number_of_steps=base(BASE_STEPS),
            loop_start=base(BASE_LOOP_START),
            loop_end=base(BASE_LOOP_END),
            loop_count=base(BASE_LOOP_COUNT),
            repeat_count=base(BASE_REPEAT),
            subdivision=base(BASE_SUBDIVISION, 2),
            step_angle_x100=base(BASE_STEP_ANGLE),
            distance_per_rev=base(BASE_DISTANCE_PER_REV, 3),
            stop_mode=base(BASE_STOP_MODE),
            mode4=base(BASE_MODE4),
            power_on_homing=base(BASE_POWER_ON_HOMING),
            steps=tuple(steps),
            unused_steps=unused,
            reserved=reserved,
        )

    def encode(self) -> bytes:
        """Return the 226 bytes of this dump, header included (A.5)."""
        out = bytearray(DUMP_SIZE)
        out[:6] = FF_AA + bytes((OP_READ, self.project, 0, 0))

        def put(k: int, data: bytes) -> None:
            off = dump_offset(0, k)
            out[off : off + len(data)] = data

        put(BASE_NUMBER, bytes((self.stored_number, self.number_of_steps)))
        put(BASE_LOOP_START, bytes((self.loop_start, self.loop_end, self.loop_count)))
        put(BASE_REPEAT, bytes((self.repeat_count,)))
        put(BASE_SUBDIVISION, _u16(self.subdivision) + bytes((self.step_angle_x100,)))
        put(BASE_DISTANCE_PER_REV, _u24(self.distance_per_rev))
        put(BASE_STOP_MODE, bytes((self.stop_mode, self.mode4, self.power_on_homing)))
        for i, k in enumerate(BASE_RESERVED):
            out[dump_offset(0, k)] = self.reserved[i]
        datas = [s.encode_data() for s in self.steps]
        datas += [
            self.unused_steps[i : i + STEP_DATA_SIZE]
            for i in range(0, len(self.unused_steps), STEP_DATA_SIZE)
        ]
        tail = self.reserved[len(BASE_RESERVED) :]
        for x, data in enumerate(datas, start=1):
            start = dump_offset(x, 0)
            out[start : start + STEP_DATA_SIZE] = data
            r = (x - 1) * len(STEP_RESERVED)
            out[start + STEP_DATA_SIZE : start + DUMP_BLOCK_SIZE] = tail[r : r + len(STEP_RESERVED)]
        return bytes(out)

    def to_project(self) -> Project:
        """Return the stored project (steps beyond ``number_of_steps`` dropped).

        Raises:
            LocalProtocolError: the stored values do not form a valid project (for
                example a cleared project with 0 steps); the message names the field.
        """
        return Project(
            number=self.stored_number,
            subdivision=self.subdivision,
            step_angle_x100=self.step_angle_x100,
            distance_per_rev=self.distance_per_rev,
            steps=self.steps,
            loop_start=self.loop_start,
            loop_end=self.loop_end,
            loop_count=self.loop_count,
            repeat_count=self.repeat_count,
        )

    @classmethod
    def from_project(
        cls,
        project: Project,
        stop_mode: int = 0,
        mode4: int = 0,
        power_on_homing: bool = False,
        reserved: bytes | None = None,
        unused_steps: bytes | None = None,
    ) -> ProjectDump:
        """Return the dump a device holding ``project`` would send.

        Args:
            project: the project.
            stop_mode: ``[0][14]``, 0 slow or 1 immediate.
            mode4: ``[0][15]``, 0..2.
            power_on_homing: ``[0][16]``.
            reserved: the 45 unlisted bytes (default zeros).
            unused_steps: data bytes of the unused step blocks (default zeros).

        Raises:
            LocalProtocolError: a value is out of range or a byte string has the wrong size.
        """
        check_choice("stop_mode", stop_mode, tuple(StopBehavior), "0 slow, 1 immediate")
        check_choice("mode4", mode4, MODE4_VALUES, "A0-13")
        n = len(project.steps)
        return cls(
            project=project.number,
            stored_number=project.number,
            number_of_steps=n,
            loop_start=project.loop_start,
            loop_end=project.loop_end,
            loop_count=project.loop_count,
            repeat_count=project.repeat_count,
            subdivision=project.subdivision,
            step_angle_x100=project.step_angle_x100,
            distance_per_rev=project.distance_per_rev,
            stop_mode=int(stop_mode),
            mode4=int(mode4),
            power_on_homing=int(bool(power_on_homing)),
            steps=project.steps,
            unused_steps=_zero_unused(n) if unused_steps is None else bytes(unused_steps),
            reserved=bytes(RESERVED_SIZE) if reserved is None else bytes(reserved),
        )
