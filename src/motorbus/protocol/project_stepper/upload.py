"""The upload sequence (doc 000 A.6): the commands that write a project, in order.

Pure: it says which commands program a :class:`Project` or one :class:`StepSpec`, and
sends nothing (``ProjectStepper.upload`` sends them and checks the replies).  It lives
beside the commands rather than in ``project``, so projects stay plain values and
``project`` never imports ``commands`` (which needs ``ProjectDump`` for ``ReadProject``).
"""

from __future__ import annotations

from motorbus.protocol.project_stepper.commands import (
    AccelAndSpeed,
    DirectionAndStartFrequency,
    DistancePerRev,
    MotorSetup,
    ProjectStepperCommand,
    RepeatCount,
    RunDistance,
    SelectProject,
    StartInput,
    StepDelay,
    StepLoop,
    StepOutput,
    StopInput,
)
from motorbus.protocol.project_stepper.project import Project, StepSpec
from motorbus.protocol.project_stepper.wire import DEFAULT_MOTOR


def step_commands(
    spec: StepSpec, step: int, motor: int = DEFAULT_MOTOR
) -> list[ProjectStepperCommand[object]]:
    """Return the seven commands 03..09 that program ``spec`` as step ``step`` (A.6).

    Raises:
        LocalProtocolError: ``step`` is not 1..10 or ``motor`` is not allowed.
    """
    return [
        RunDistance(step, spec.run_distance, motor=motor),
        DirectionAndStartFrequency(step, spec.direction, spec.start_hz, motor=motor),
        AccelAndSpeed(step, spec.accel_hz, spec.speed_rpm, motor=motor),
        StepOutput(step, spec.output, motor=motor),
        StepDelay(step, spec.delay_ms, motor=motor),
        StartInput(step, spec.start_input, motor=motor),
        StopInput(step, spec.stop_input, motor=motor),
    ]


def project_commands(
    project: Project, motor: int = DEFAULT_MOTOR
) -> list[ProjectStepperCommand[object]]:
    """Return the programming sequence of A.6 for ``project``, without the final SaveProject.

    SelectProject, MotorSetup, DistancePerRev, then 03..09 for each step, then StepLoop
    and RepeatCount (always sent, so stale loop settings are overwritten).

    Raises:
        LocalProtocolError: ``motor`` is not allowed (A0-02).
    """
    out: list[ProjectStepperCommand[object]] = [
        SelectProject(project.number, len(project.steps)),
        MotorSetup(project.subdivision, project.step_angle_x100, motor=motor),
        DistancePerRev(project.distance_per_rev, motor=motor),
    ]
    for i, spec in enumerate(project.steps, start=1):
        out += step_commands(spec, i, motor)
    out.append(StepLoop(project.loop_start, project.loop_end, project.loop_count))
    out.append(RepeatCount(project.repeat_count))
    return out
