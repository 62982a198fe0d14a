"""Program a two-step project into the stepper project controller, run it, await EE DD."""

from __future__ import annotations

from _sim import parser, port_or_simulator

import motorbus
from motorbus.protocol import project_stepper as ps


async def main(port: str) -> None:
    transport = motorbus.open_transport(port, baudrate=9600)
    async with motorbus.Bus(transport, families=[motorbus.Family.PROJECT_STEPPER]) as bus:
        stepper = motorbus.ProjectStepper(bus, motor=3)
        out = ps.StepSpec(
            run_distance=2,
            direction=ps.RotationDirection.FORWARD,
            start_hz=100,
            accel_hz=50,
            speed_rpm=300,
            delay_ms=200,
        )
        back = ps.StepSpec(
            run_distance=2,
            direction=ps.RotationDirection.REVERSE,
            start_hz=100,
            accel_hz=50,
            speed_rpm=300,
        )
        project = ps.Project(
            1, subdivision=8, step_angle_x100=180, distance_per_rev=1, steps=(out, back)
        )
        dump = await stepper.upload(project)  # programs, saves, reads back with 0x3E
        print(f"project {dump.project} verified: {dump.number_of_steps} steps")
        await stepper.run_project(1, timeout=30)  # returns when EE DD arrives
        print("project finished (EE DD)")


if __name__ == "__main__":
    args = parser(__doc__).parse_args()
    with port_or_simulator(args, ["project-stepper"], 9600) as port:
        motorbus.run(main(port))
